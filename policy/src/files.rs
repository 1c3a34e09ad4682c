//! Reading a checkpoint's side files (`config.json`, `norm_stats.json`, `tokenizer.json`):
//! regular files only, with a size cap. At the bottom of the crate with the error type.

use std::path::Path;

use crate::error::PolicyError;

/// The largest side file of a checkpoint read (`config.json`, `norm_stats.json`,
/// `tokenizer.json`: a real PaliGemma `tokenizer.json` is ~17 MB).
pub const MAX_SIDE_FILE_BYTES: u64 = 64 << 20;

/// Reads `path` whole, if it is a regular file of at most `max` bytes: a FIFO, a device such as
/// `/dev/zero` or an oversized file is a clear error, never a hang or an unbounded read.
pub fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>, PolicyError> {
    use std::io::Read;
    let io = |e: String| PolicyError::Io(format!("{}: {e}", path.display()));
    let meta = std::fs::metadata(path).map_err(|e| io(e.to_string()))?;
    if !meta.is_file() {
        return Err(io("not a regular file".into()));
    }
    if meta.len() > max {
        return Err(io(format!("{} bytes; at most {max} are read", meta.len())));
    }
    let mut buf = Vec::with_capacity(meta.len() as usize);
    std::fs::File::open(path)
        .map_err(|e| io(e.to_string()))?
        .take(max + 1)
        .read_to_end(&mut buf)
        .map_err(|e| io(e.to_string()))?;
    if buf.len() as u64 > max {
        return Err(io(format!("grew beyond {max} bytes while read")));
    }
    Ok(buf)
}

/// [`read_bounded`] with [`MAX_SIDE_FILE_BYTES`], as UTF-8 text.
pub fn read_side_file(path: &Path) -> Result<String, PolicyError> {
    String::from_utf8(read_bounded(path, MAX_SIDE_FILE_BYTES)?)
        .map_err(|_| PolicyError::Io(format!("{}: not UTF-8 text", path.display())))
}
