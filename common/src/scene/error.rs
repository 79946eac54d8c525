//! Scene loading errors, each naming the file and the element.
//!
//! The coordinator maps these to HTTP statuses: [`SceneError::LimitExceeded`] is a 413-style
//! refusal, [`SceneError::ForbiddenUri`] and [`SceneError::Invalid`] are 422 (invalid scene),
//! [`SceneError::Io`] is a server-side problem unless the file was uploaded.

/// An error loading a scene; the message names the file and the glTF element.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file is not valid glTF, or one element of it is broken. `message` starts with the
    /// element, e.g. `mesh 3 primitive 1: accessor 7: needs 1200 bytes, bufferView 2 has 600`.
    #[error("{file}: {message}")]
    Invalid { file: String, message: String },
    /// An external URI that is not allowed: absolute, with `..`, with a scheme other than
    /// `data:`, or external while no base directory was given. `element` is e.g. `buffer 0`.
    #[error("{file}: {element} uri {uri:?}: {reason}")]
    ForbiddenUri { file: String, element: String, uri: String, reason: String },
    /// A limit of [`LoadOptions`](super::LoadOptions) was exceeded; `limit` is the option's name.
    #[error("{file}: {element}: {actual} exceeds the limit {limit} = {max}")]
    LimitExceeded { file: String, element: String, limit: &'static str, actual: u64, max: u64 },
    /// Reading the file or one of its external files failed.
    #[error("{file}: {element}: {source}")]
    Io {
        file: String,
        element: String,
        #[source]
        source: std::io::Error,
    },
}

impl SceneError {
    /// The file the error is about (the scene's name).
    pub fn file(&self) -> &str {
        match self {
            Self::Invalid { file, .. }
            | Self::ForbiddenUri { file, .. }
            | Self::LimitExceeded { file, .. }
            | Self::Io { file, .. } => file,
        }
    }
}
