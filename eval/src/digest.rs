//! Content digests for the keys of saved results: a result is reused only
//! when what produced it is byte for byte the same, not merely at the same path.

use std::path::Path;

/// 64-bit FNV-1a, continuing from `h` (start from [`FNV_START`]).
pub fn fnv1a(mut h: u64, bytes: &[u8]) -> u64 {
    for &b in bytes {
        h = (h ^ b as u64).wrapping_mul(0x0100_0000_01b3);
    }
    h
}

pub const FNV_START: u64 = 0xcbf2_9ce4_8422_2325;

/// A model folder's path and a digest of the files directly in it (manifest,
/// graphs, weights; not `reference/`, and not its card or other `.md` prose,
/// which makes no frame), in name order: re-exported weights at the same path
/// get a new key, a reworded card does not.
pub fn model_key(dir: &Path) -> Result<String, std::io::Error> {
    let reading = |p: &Path, e: std::io::Error| std::io::Error::new(e.kind(), format!("reading {}: {e}", p.display()));
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .map_err(|e| reading(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.extension().is_none_or(|e| e != "md"))
        .collect();
    files.sort();
    let mut h = FNV_START;
    for f in files {
        h = fnv1a(h, f.file_name().unwrap_or_default().as_encoded_bytes());
        h = fnv1a(h, &std::fs::read(&f).map_err(|e| reading(&f, e))?);
    }
    Ok(format!("{} #{h:016x}", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_key_follows_the_weights_not_the_card() {
        let dir = std::env::temp_dir().join(format!("worldpack-digest-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("model.onnx"), b"weights").unwrap();
        let before = model_key(&dir).unwrap();
        std::fs::write(dir.join("MODEL.md"), b"# a card").unwrap();
        assert_eq!(model_key(&dir).unwrap(), before, "a card is prose");
        std::fs::write(dir.join("model.onnx"), b"other weights").unwrap();
        assert_ne!(model_key(&dir).unwrap(), before, "new weights are a new model");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
