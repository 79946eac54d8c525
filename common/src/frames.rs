//! Frame sets: which frames of an animation a job or a local render covers.
//!
//! The syntax is the one render farms share (Flamenco, OpenCue, Deadline): comma-separated items,
//! each a frame `7`, a range `1-100` (both ends included) or a stepped range `1-100x5`
//! (1, 6, 11, ... 96). Frames may be negative (`-10--1`). Frames are listed in the order
//! written, duplicates removed (the first occurrence stays).

use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::fmt;

use crate::job::MAX_FRAME;

/// Most frames one set may list (a job keeps a state per frame).
pub const MAX_FRAMES: usize = 100_000;

/// A parsed frame set. Serialized as its string form.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameSet {
    spec: String,
    frames: Vec<i32>,
}

/// Why a frame set was refused; the message quotes the item at fault.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("frames {spec:?}: {message}")]
pub struct FrameSetError {
    pub spec: String,
    pub message: String,
}

impl FrameSet {
    /// Parses `"1-100"`, `"1-100x5"`, `"1,5,10-20"`.
    pub fn parse(spec: &str) -> Result<Self, FrameSetError> {
        let err = |message: String| FrameSetError { spec: spec.chars().take(64).collect(), message };
        if spec.len() > 4096 {
            return Err(err(format!("the set is {} bytes long; the limit is 4096", spec.len())));
        }
        let mut frames = Vec::new();
        let mut seen = HashSet::new();
        let mut steps = 0i64;
        for item in spec.split(',') {
            let item = item.trim();
            if item.is_empty() {
                return Err(err("empty item (write e.g. \"1-24\" or \"1,5,10-20\")".into()));
            }
            let (range, step) = match item.split_once(['x', 'X']) {
                Some((r, s)) => {
                    let step: u32 = s
                        .trim()
                        .parse()
                        .map_err(|_| err(format!("{item:?}: the step after 'x' must be a positive integer")))?;
                    if step == 0 {
                        return Err(err(format!("{item:?}: the step must be at least 1")));
                    }
                    (r.trim(), step)
                }
                None => (item, 1),
            };
            let (first, last) = split_range(range).map_err(|m| err(format!("{item:?}: {m}")))?;
            if first > last {
                return Err(err(format!("{item:?}: the range runs backwards ({first} > {last})")));
            }
            // Bounded before iterating: repeated large ranges must not cost time either.
            let count = (i64::from(last) - i64::from(first)) / i64::from(step) + 1;
            steps += count;
            if count > MAX_FRAMES as i64 || steps > 4 * MAX_FRAMES as i64 {
                return Err(err(format!("more than {MAX_FRAMES} frames")));
            }
            let mut f = i64::from(first);
            while f <= i64::from(last) {
                let frame = f as i32;
                if seen.insert(frame) {
                    if frames.len() == MAX_FRAMES {
                        return Err(err(format!("more than {MAX_FRAMES} frames")));
                    }
                    frames.push(frame);
                }
                f += i64::from(step);
            }
        }
        Ok(Self { spec: spec.trim().to_string(), frames })
    }

    /// One frame.
    pub fn single(frame: i32) -> Self {
        Self { spec: frame.to_string(), frames: vec![frame] }
    }

    /// The frames, in the order written.
    pub fn frames(&self) -> &[i32] {
        &self.frames
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// The set as written.
    pub fn spec(&self) -> &str {
        &self.spec
    }
}

/// `"a"` or `"a-b"`, where `a` and `b` may have a leading minus sign.
fn split_range(s: &str) -> Result<(i32, i32), String> {
    let frame = |t: &str| -> Result<i32, String> {
        let t = t.trim();
        let v: i64 = t.parse().map_err(|_| format!("{t:?} is not a frame number"))?;
        if v.unsigned_abs() > u64::from(MAX_FRAME.unsigned_abs()) {
            return Err(format!("frame {v} is beyond +-{MAX_FRAME}"));
        }
        Ok(v as i32)
    };
    // The separating '-' is the first one after the first character (which may be a sign).
    match s.char_indices().skip(1).find(|&(_, c)| c == '-') {
        Some((i, _)) => Ok((frame(&s[..i])?, frame(&s[i + 1..])?)),
        None => {
            let f = frame(s)?;
            Ok((f, f))
        }
    }
}

impl fmt::Display for FrameSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.spec)
    }
}

impl std::str::FromStr for FrameSet {
    type Err = FrameSetError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::parse(s)
    }
}

impl Serialize for FrameSet {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.spec)
    }
}

impl<'de> Deserialize<'de> for FrameSet {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        Self::parse(&s).map_err(serde::de::Error::custom)
    }
}

/// Replaces the run of `#` in `pattern` by `frame`, zero-padded to the run's length
/// (`shot.####.exr`, 7 -> `shot.0007.exr`; a negative frame keeps its sign: `shot.-007.exr`).
/// A pattern without `#` gets `.NNNN` before its extension.
pub fn frame_path(pattern: &str, frame: i32) -> String {
    match pattern.find('#') {
        Some(start) => {
            let len = pattern[start..].chars().take_while(|&c| c == '#').count();
            let number = if frame < 0 {
                format!("-{:0width$}", frame.unsigned_abs(), width = len.saturating_sub(1))
            } else {
                format!("{frame:0len$}")
            };
            format!("{}{}{}", &pattern[..start], number, &pattern[start + len..])
        }
        None => {
            let p = std::path::Path::new(pattern);
            match (p.file_stem(), p.extension()) {
                (Some(stem), Some(ext)) => {
                    let file = format!("{}.{frame:04}.{}", stem.to_string_lossy(), ext.to_string_lossy());
                    p.with_file_name(file).to_string_lossy().into_owned()
                }
                _ => format!("{pattern}.{frame:04}"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn parses_the_farm_syntax() {
        assert_eq!(FrameSet::parse("1-5").expect("accepted").frames(), &[1, 2, 3, 4, 5]);
        assert_eq!(FrameSet::parse("1-20x5").expect("accepted").frames(), &[1, 6, 11, 16]);
        assert_eq!(FrameSet::parse("1,5,10-12").expect("accepted").frames(), &[1, 5, 10, 11, 12]);
        assert_eq!(FrameSet::parse(" 3 , 1-3 ").expect("accepted").frames(), &[3, 1, 2]);
        assert_eq!(FrameSet::parse("-2-1").expect("accepted").frames(), &[-2, -1, 0, 1]);
        assert_eq!(FrameSet::parse("-3--2").expect("accepted").frames(), &[-3, -2]);
        assert_eq!(FrameSet::parse("7").expect("accepted").frames(), &[7]);
    }

    #[test]
    fn refusals_name_the_item() {
        for (spec, needle) in [
            ("", "empty item"),
            ("1,,2", "empty item"),
            ("5-1", "backwards"),
            ("1-10x0", "at least 1"),
            ("1-10xq", "step"),
            ("a-3", "\"a\" is not a frame number"),
            ("1-99999999999", "beyond"),
            ("0-200000", "more than"),
            ("1-90000,1-90000,1-90000,1-90000,1-90000", "more than"),
        ] {
            let e = FrameSet::parse(spec).expect_err("refused").to_string();
            assert!(e.contains(needle), "{spec:?}: {e}");
        }
    }

    #[test]
    fn frame_paths() {
        assert_eq!(frame_path("out/shot.####.exr", 7), "out/shot.0007.exr");
        assert_eq!(frame_path("out/shot.#.exr", 123), "out/shot.123.exr");
        assert_eq!(frame_path("shot.####.exr", -7), "shot.-007.exr");
        assert_eq!(frame_path("out/shot.exr", 12), "out/shot.0012.exr");
    }

    #[test]
    fn serde_round_trip() {
        let f: FrameSet = serde_json::from_str("\"1-10x3\"").expect("accepted");
        assert_eq!(f.frames(), &[1, 4, 7, 10]);
        assert_eq!(serde_json::to_string(&f).expect("accepted"), "\"1-10x3\"");
        assert!(serde_json::from_str::<FrameSet>("\"1-\"").is_err());
    }

    proptest! {
        /// Whatever the input, parsing returns (never panics) and a set it accepts lists
        /// distinct frames within the limits.
        #[test]
        fn parse_never_panics(s in "[-0-9x,X ]{0,24}") {
            if let Ok(f) = FrameSet::parse(&s) {
                let unique: HashSet<_> = f.frames().iter().collect();
                prop_assert_eq!(unique.len(), f.len());
                prop_assert!(f.len() <= MAX_FRAMES);
            }
        }
    }
}
