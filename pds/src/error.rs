use std::path::PathBuf;

/// What is wrong with a product, naming the file and the keyword or byte offset.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: malformed label: {source}")]
    Label {
        path: PathBuf,
        source: crate::odl::ParseError,
    },
    #[error("{path}: the label has no {keyword}")]
    Missing { path: PathBuf, keyword: String },
    #[error("{path}: {keyword}: {why}")]
    Invalid {
        path: PathBuf,
        keyword: String,
        why: String,
    },
    #[error("{path}: {why}")]
    Size { path: PathBuf, why: String },
    /// A pointer names a file that is not beside the label (in any letter case).
    #[error("{path}: pointer: points to {file}, which is not in {}", dir.display())]
    Absent {
        path: PathBuf,
        file: String,
        dir: PathBuf,
    },
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub(crate) fn invalid(path: &std::path::Path, keyword: &str, why: impl Into<String>) -> Self {
        Error::Invalid {
            path: path.into(),
            keyword: keyword.into(),
            why: why.into(),
        }
    }
    pub(crate) fn missing(path: &std::path::Path, keyword: &str) -> Self {
        Error::Missing {
            path: path.into(),
            keyword: keyword.into(),
        }
    }
}
