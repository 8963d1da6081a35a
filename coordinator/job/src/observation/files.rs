//! Reading and writing whole files safely: a size cap checked before reading, and writes that
//! land under their name only when complete.

use super::*;

/// Reads a whole file of at most `limit` bytes (its size is checked before reading).
pub fn read_capped(
    path: &Path,
    limit: u64,
    what: &'static str,
) -> Result<Vec<u8>, ObservationError> {
    let read_error = |source| ObservationError::Read {
        file: display(path),
        source,
    };
    let file = std::fs::File::open(path).map_err(read_error)?;
    let bytes = file.metadata().map_err(read_error)?.len();
    if bytes > limit {
        return Err(ObservationError::FileTooLarge {
            file: display(path),
            what,
            bytes,
            limit,
        });
    }
    let mut out = Vec::with_capacity(usize::try_from(bytes).unwrap_or(0));
    // `take` bounds a file that grows while it is read.
    std::io::Read::read_to_end(&mut std::io::Read::take(file, limit + 1), &mut out)
        .map_err(read_error)?;
    if out.len() as u64 > limit {
        return Err(ObservationError::FileTooLarge {
            file: display(path),
            what,
            bytes: out.len() as u64,
            limit,
        });
    }
    Ok(out)
}

/// Writes `data` to `path` atomically: a temporary file beside it, then a rename.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> Result<()>,
) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("cannot create directory {}", dir.display()))?;
    let mut tmp = tempfile::Builder::new()
        .prefix(".scatterfarm-")
        .suffix(".tmp")
        .tempfile_in(&dir)
        .with_context(|| format!("cannot create a temporary file in {}", dir.display()))?;
    {
        let mut w = BufWriter::new(tmp.as_file_mut());
        write(&mut w)?;
        w.flush()
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    tmp.as_file()
        .sync_all()
        .with_context(|| format!("cannot sync {}", path.display()))?;
    tmp.persist(path)
        .with_context(|| format!("cannot move the finished file to {}", path.display()))?;
    Ok(())
}
