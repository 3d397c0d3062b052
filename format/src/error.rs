use std::path::PathBuf;

/// Everything that can be wrong with an archive. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The OS error is part of the message, not a source, so `{:#}` does not repeat it.
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}: not a regular file (a Canopy archive is a file, not a directory or device)")]
    NotAFile { path: PathBuf },
    #[error("{path}: not a Canopy archive (bad magic); a scene (.glb, .gltf, .ply, .obj) renders once converted: canopy convert {path} -o SCENE.canopy")]
    BadMagic { path: PathBuf },
    #[error("{path}: archive format version {major}.{minor} is newer than this canopy reads ({}.x); upgrade canopy", crate::VERSION_MAJOR)]
    NewerVersion {
        path: PathBuf,
        major: u16,
        minor: u16,
    },
    #[error("{path}: archive format version {major}.{minor} is older than this canopy reads ({}.x); convert the source again with `canopy convert`", crate::VERSION_MAJOR)]
    OlderVersion {
        path: PathBuf,
        major: u16,
        minor: u16,
    },
    #[error("{path}: truncated archive: {what} needs bytes up to {needed}, file has {len}")]
    Truncated {
        path: PathBuf,
        what: String,
        needed: u64,
        len: u64,
    },
    #[error("{path}: corrupt archive: {what}")]
    Corrupt { path: PathBuf, what: String },
    #[error("{path}: page {page}: {what}")]
    BadPage {
        path: PathBuf,
        page: u32,
        what: String,
    },
    #[error("{path}: not a Canopy bake file (bad magic)")]
    NotRadiance { path: PathBuf },
    #[error("{path}: corrupt bake file: {what}")]
    BadRadiance { path: PathBuf, what: String },
    #[error("{path}: baked for a different archive than {archive} ({what}); bake it again with `canopy bake`")]
    WrongArchive {
        path: PathBuf,
        archive: PathBuf,
        what: String,
    },
}

pub type Result<T> = std::result::Result<T, FormatError>;
