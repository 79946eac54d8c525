//! Scene loading errors, each naming the file and the element.

/// An error loading a scene; the message names the file and the glTF element.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{file}: {message}")]
    Invalid { file: String, message: String },
}
