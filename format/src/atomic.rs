//! Output files that appear at their path only once complete: the bytes go to an unnamed
//! file in the target's directory (`O_TMPFILE`: the kernel reclaims it if the process dies,
//! even by SIGKILL) or, where the filesystem cannot do that, to a hidden `.NAME.tmp-PID`
//! beside it, removed if the writer is dropped and by the next writer into that directory
//! once its process is gone. `commit` writes the header last, fsyncs, and renames.

use crate::error::{FormatError, Result};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

pub fn io(path: &Path) -> impl FnOnce(std::io::Error) -> FormatError + '_ {
    move |source| FormatError::Io {
        path: path.to_path_buf(),
        error: source,
    }
}

pub struct AtomicFile {
    path: PathBuf,
    /// The hidden temporary name (`.NAME.tmp-PID`), for messages; the file has that name
    /// only where the filesystem cannot make unnamed files.
    tmp: PathBuf,
    named: bool,
    /// Never named: scratch output read back by this process.
    anonymous: bool,
    out: Option<BufWriter<File>>,
    /// Bytes written so far, the reserved header included.
    len: u64,
    done: bool,
}

impl AtomicFile {
    /// Starts a file that will appear at `path` on `commit`, beginning with `header_len`
    /// zero bytes that `commit` overwrites.
    pub fn create(path: &Path, header_len: usize) -> Result<AtomicFile> {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
        tmpfile::remove_orphans(&dir, &name);
        let (file, named) = match tmpfile::unnamed(&dir) {
            Some(f) => (f, false),
            None => (File::create(&tmp).map_err(io(path))?, true),
        };
        AtomicFile::start(path, tmp, named, file, header_len)
    }

    /// A file that never gets a name (it lives until dropped), for scratch output.
    pub fn anonymous(what: &Path, header_len: usize) -> Result<AtomicFile> {
        let file = tempfile::tempfile().map_err(io(what))?;
        let mut f = AtomicFile::start(what, what.to_path_buf(), false, file, header_len)?;
        f.anonymous = true;
        Ok(f)
    }

    fn start(
        path: &Path,
        tmp: PathBuf,
        named: bool,
        file: File,
        header_len: usize,
    ) -> Result<AtomicFile> {
        let mut out = BufWriter::with_capacity(1 << 20, file);
        out.write_all(&vec![0u8; header_len]).map_err(io(&tmp))?;
        Ok(AtomicFile {
            path: path.to_path_buf(),
            tmp,
            named,
            anonymous: false,
            out: Some(out),
            len: header_len as u64,
            done: false,
        })
    }

    /// The path the file will have.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes written so far.
    pub fn len(&self) -> u64 {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn write_all(&mut self, bytes: &[u8]) -> Result<()> {
        let out = self.out.as_mut().expect("file written after commit");
        out.write_all(bytes).map_err(io(&self.tmp))?;
        self.len += bytes.len() as u64;
        Ok(())
    }

    /// Writes `header` at offset 0, syncs, and names the file (`anonymous` files stay
    /// unnamed). Returns the file, for a reader that wants it without reopening.
    pub fn commit(mut self, header: &[u8]) -> Result<File> {
        let out = self.out.take().expect("commit called twice");
        let tmp = self.tmp.clone();
        let mut file = out.into_inner().map_err(|e| FormatError::Io {
            path: tmp.clone(),
            error: e.into_error(),
        })?;
        file.seek(SeekFrom::Start(0)).map_err(io(&tmp))?;
        file.write_all(header).map_err(io(&tmp))?;
        if self.anonymous {
            self.done = true;
            return Ok(file);
        }
        file.sync_all().map_err(io(&tmp))?;
        if self.named {
            std::fs::rename(&tmp, &self.path).map_err(io(&self.path))?;
        } else {
            tmpfile::link(&file, &self.path, &tmp).map_err(io(&self.path))?;
        }
        self.done = true;
        if let Some(dir) = self.path.parent().filter(|d| !d.as_os_str().is_empty()) {
            // Persist the rename; not every filesystem supports syncing a directory.
            let _ = File::open(dir).and_then(|d| d.sync_all());
        }
        Ok(file)
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if !self.done && self.named {
            self.out.take();
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Unnamed output files and the named fallback's clean-up.
mod tmpfile {
    use std::fs::File;
    use std::path::Path;

    /// An unnamed read-write file in `dir`, where the OS and filesystem support it.
    #[cfg(target_os = "linux")]
    pub fn unnamed(dir: &Path) -> Option<File> {
        use std::os::unix::ffi::OsStrExt;
        use std::os::unix::io::FromRawFd;
        let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
        // SAFETY: a valid C string; the descriptor is owned by the File on success.
        let fd = unsafe {
            libc::open(
                c.as_ptr(),
                libc::O_TMPFILE | libc::O_RDWR | libc::O_CLOEXEC,
                0o644,
            )
        };
        // SAFETY: `fd` was just opened and nothing else owns it.
        (fd >= 0).then(|| unsafe { File::from_raw_fd(fd) })
    }

    #[cfg(not(target_os = "linux"))]
    pub fn unnamed(_dir: &Path) -> Option<File> {
        None
    }

    /// Gives an unnamed file the name `dest`, replacing what is there: linked under `tmp`
    /// first and renamed over `dest` (link cannot replace), so `dest` is never partial.
    #[cfg(target_os = "linux")]
    pub fn link(file: &File, dest: &Path, tmp: &Path) -> std::io::Result<()> {
        use std::os::unix::ffi::OsStrExt;
        use std::os::unix::io::AsRawFd;
        let from = std::ffi::CString::new(format!("/proc/self/fd/{}", file.as_raw_fd()))?;
        let to = std::ffi::CString::new(tmp.as_os_str().as_bytes())?;
        let _ = std::fs::remove_file(tmp);
        // SAFETY: valid C strings; linkat reads them only.
        let r = unsafe {
            libc::linkat(
                libc::AT_FDCWD,
                from.as_ptr(),
                libc::AT_FDCWD,
                to.as_ptr(),
                libc::AT_SYMLINK_FOLLOW,
            )
        };
        if r != 0 {
            return Err(std::io::Error::last_os_error());
        }
        std::fs::rename(tmp, dest).inspect_err(|_| {
            let _ = std::fs::remove_file(tmp);
        })
    }

    #[cfg(not(target_os = "linux"))]
    pub fn link(_file: &File, _dest: &Path, _tmp: &Path) -> std::io::Result<()> {
        unreachable!("unnamed files exist only on Linux")
    }

    /// Removes `.NAME.tmp-PID` files in `dir` whose process no longer exists (left by a
    /// writer killed where unnamed files were not available).
    pub fn remove_orphans(dir: &Path, name: &str) {
        let prefix = format!(".{name}.tmp-");
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            let file = e.file_name();
            let Some(pid) = file
                .to_str()
                .and_then(|f| f.strip_prefix(&prefix))
                .and_then(|p| p.parse::<i32>().ok())
            else {
                continue;
            };
            if !alive(pid) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }

    #[cfg(unix)]
    fn alive(pid: i32) -> bool {
        // SAFETY: signal 0 only checks that the process exists.
        pid > 0
            && (unsafe { libc::kill(pid, 0) } == 0
                || std::io::Error::last_os_error().raw_os_error() != Some(libc::ESRCH))
    }

    #[cfg(not(unix))]
    fn alive(_pid: i32) -> bool {
        true
    }
}
