//! NumPy `.npy` files (format 1.0), so a suite reads with `numpy.load` and
//! nothing else. Little-endian, C order.

use std::io::{self, Read, Write};

/// Element types the suites use.
pub trait Element: Copy {
    const DESCR: &'static str;
    fn write_le(items: &[Self], out: &mut Vec<u8>);
    fn read_le(bytes: &[u8]) -> Vec<Self>;
}

macro_rules! element {
    ($t:ty, $descr:literal) => {
        impl Element for $t {
            const DESCR: &'static str = $descr;
            fn write_le(items: &[Self], out: &mut Vec<u8>) {
                out.reserve(items.len() * size_of::<$t>());
                for v in items {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
            fn read_le(bytes: &[u8]) -> Vec<Self> {
                bytes.chunks_exact(size_of::<$t>()).map(|c| <$t>::from_le_bytes(c.try_into().unwrap())).collect()
            }
        }
    };
}

element!(u8, "|u1");
element!(u16, "<u2");
element!(i32, "<i4");
element!(f32, "<f4");
element!(f64, "<f8");
element!(i64, "<i8");

/// The whole file: header padded to 64 bytes, then the data.
pub fn encode<T: Element>(shape: &[usize], data: &[T]) -> Vec<u8> {
    assert_eq!(shape.iter().product::<usize>(), data.len(), "npy shape does not match the data");
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_text = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut header = format!("{{'descr': '{}', 'fortran_order': False, 'shape': {}, }}", T::DESCR, shape_text);
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + std::mem::size_of_val(data));
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    T::write_le(data, &mut out);
    out
}

pub fn write<T: Element>(path: &std::path::Path, shape: &[usize], data: &[T]) -> io::Result<()> {
    let mut f = std::fs::File::create(path)?;
    f.write_all(&encode(shape, data))?;
    f.sync_all()
}

/// Reads a file this module wrote (or any little-endian C-order 1.0 file of
/// the same element type): the shape and the data.
pub fn read<T: Element>(path: &std::path::Path) -> io::Result<(Vec<usize>, Vec<T>)> {
    let mut bytes = Vec::new();
    std::fs::File::open(path)?.read_to_end(&mut bytes)?;
    let bad = |why: &str| io::Error::new(io::ErrorKind::InvalidData, format!("{}: {why}", path.display()));
    if bytes.len() < 10 || &bytes[..8] != b"\x93NUMPY\x01\x00" {
        return Err(bad("not a version 1.0 .npy file"));
    }
    let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = std::str::from_utf8(bytes.get(10..10 + header_len).ok_or_else(|| bad("truncated header"))?)
        .map_err(|_| bad("header is not UTF-8"))?;
    if !header.contains(&format!("'descr': '{}'", T::DESCR)) || header.contains("'fortran_order': True") {
        return Err(bad(&format!("expected dtype {} in C order, header is {header}", T::DESCR)));
    }
    let shape_text = header.split("'shape': (").nth(1).and_then(|s| s.split(')').next()).ok_or_else(|| bad("no shape"))?;
    let shape: Vec<usize> = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().map_err(|_| bad("bad shape")))
        .collect::<Result<_, _>>()?;
    let data = T::read_le(&bytes[10 + header_len..]);
    if data.len() != shape.iter().product::<usize>() {
        return Err(bad("data length does not match the shape"));
    }
    Ok((shape, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_alignment() {
        let dir = std::env::temp_dir().join(format!("npy-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5).collect();
        write(&path, &[2, 3, 4], &data).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + header_len) % 64, 0);
        let (shape, back) = read::<f32>(&path).unwrap();
        assert_eq!(shape, vec![2, 3, 4]);
        assert_eq!(back, data);
        assert!(read::<u8>(&path).is_err());
        write(&path, &[5], &[1u16, 2, 3, 4, 5]).unwrap();
        assert_eq!(read::<u16>(&path).unwrap(), (vec![5], vec![1, 2, 3, 4, 5]));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
