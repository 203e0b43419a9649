//! Pictures for people: PNG frames, a false-colour depth image, and a
//! top-down map of a trajectory over the terrain.

use std::io;
use std::path::Path;

use crate::blocks::{Block, Face};
use crate::terrain::World;
use crate::trajectory::{Phase, Trajectory};

/// Writes 8-bit RGB pixels (row-major, top-left first) as a PNG.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> io::Result<()> {
    std::fs::write(path, encode_png(width, height, rgb))
}

/// 8-bit RGB pixels (row-major, top-left first) as PNG bytes.
pub fn encode_png(width: u32, height: u32, rgb: &[u8]) -> Vec<u8> {
    assert_eq!(rgb.len(), (width * height * 3) as usize, "encode_png: not an RGB image of the given size");
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.write_header().and_then(|mut w| w.write_image_data(rgb)).expect("encoding a PNG into memory");
    out
}

/// A PNG's pixels as 8-bit RGB, with its width and height: RGB, RGBA
/// (alpha dropped), grey (with or without alpha) and palette images, 16-bit
/// channels cut to their high byte. The error says what is wrong with it.
pub fn decode_rgb(bytes: &[u8]) -> Result<(Vec<u8>, u32, u32), String> {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(|e| format!("not a PNG: {e}"))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| format!("broken PNG: {e}"))?;
    let px = (info.width * info.height) as usize;
    let rgb = match info.color_type {
        png::ColorType::Rgb => buf[..px * 3].to_vec(),
        png::ColorType::Rgba => buf[..px * 4].chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
        png::ColorType::Grayscale => buf[..px].iter().flat_map(|&g| [g, g, g]).collect(),
        png::ColorType::GrayscaleAlpha => buf[..px * 2].chunks_exact(2).flat_map(|p| [p[0], p[0], p[0]]).collect(),
        png::ColorType::Indexed => return Err("a palette the decoder did not expand".into()),
    };
    Ok((rgb, info.width, info.height))
}

/// Depth in millimetres (0 = nothing within range) as a 16-bit grayscale PNG.
pub fn encode_depth_png16(width: u32, height: u32, depth_mm: &[u16]) -> Vec<u8> {
    assert_eq!(depth_mm.len(), (width * height) as usize, "encode_depth_png16: not a depth map of the given size");
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    let bytes: Vec<u8> = depth_mm.iter().flat_map(|d| d.to_be_bytes()).collect(); // PNG samples are big-endian
    encoder.write_header().and_then(|mut w| w.write_image_data(&bytes)).expect("encoding a PNG into memory");
    out
}

/// A 16-bit grayscale PNG's samples (millimetres), with its width and height.
pub fn decode_depth_png16(bytes: &[u8]) -> Result<(Vec<u16>, u32, u32), String> {
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().map_err(|e| format!("not a PNG: {e}"))?;
    let info = reader.info();
    if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Sixteen {
        return Err(format!("must be 16-bit grayscale (millimetres), got {:?} {:?}", info.color_type, info.bit_depth));
    }
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| format!("broken PNG: {e}"))?;
    let px = (info.width * info.height) as usize;
    Ok((buf[..px * 2].chunks_exact(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect(), info.width, info.height))
}

/// Depth as colour: near is bright yellow, far is deep violet, sky black.
/// `max_depth` maps to the far end of the ramp.
pub fn depth_to_rgb(depth: &[f32], max_depth: f32) -> Vec<u8> {
    const STOPS: [[f32; 3]; 4] = [[252.0, 230.0, 90.0], [230.0, 100.0, 60.0], [140.0, 40.0, 120.0], [40.0, 10.0, 80.0]];
    depth
        .iter()
        .flat_map(|&d| {
            if !d.is_finite() {
                return [0, 0, 0];
            }
            let t = (d / max_depth).clamp(0.0, 1.0) * (STOPS.len() - 1) as f32;
            let i = (t as usize).min(STOPS.len() - 2);
            let f = t - i as f32;
            [0, 1, 2].map(|c| (STOPS[i][c] + (STOPS[i + 1][c] - STOPS[i][c]) * f).round() as u8)
        })
        .collect()
}

/// A top-down map of the trajectory's surroundings, `scale` pixels per
/// block (at least; small maps are drawn larger): terrain coloured by its top block and shaded by height, the path
/// (outbound orange, return magenta), A white, goals black.
pub fn top_down(world: &World, trajectory: &Trajectory, scale: u32) -> (u32, u32, Vec<u8>) {
    let xs = trajectory.steps.iter().map(|s| s.state.feet[0]);
    let zs = trajectory.steps.iter().map(|s| s.state.feet[2]);
    let margin = 8.0;
    let (x0, x1) = (xs.clone().fold(f64::MAX, f64::min) - margin, xs.fold(f64::MIN, f64::max) + margin);
    let (z0, z1) = (zs.clone().fold(f64::MAX, f64::min) - margin, zs.fold(f64::MIN, f64::max) + margin);
    let (bx0, bz0) = (x0.floor() as i32, z0.floor() as i32);
    let (bw, bh) = ((x1.ceil() as i32 - bx0) as u32, (z1.ceil() as i32 - bz0) as u32);
    let scale = scale.max(320 / bw.max(bh).max(1));
    let (w, h) = (bw * scale, bh * scale);
    let mut img = vec![0u8; (w * h * 3) as usize];
    for bz in 0..bh as i32 {
        for bx in 0..bw as i32 {
            let (x, z) = (bx0 + bx, bz0 + bz);
            let colour = match world.top(x, z) {
                Some(y) => {
                    let block = world.get(x, y, z);
                    let base = block.texel(Face::Top, [x, y, z], 3, 3);
                    let light = if block == Block::Water { 1.0 } else { 0.55 + 0.45 * (y as f64 / 40.0).min(1.0) };
                    base.map(|c| (c * light).clamp(0.0, 255.0) as u8)
                }
                None => [0, 0, 0],
            };
            for py in 0..scale {
                for px in 0..scale {
                    put(&mut img, w, h, (bx as u32 * scale + px) as i64, (bz as u32 * scale + py) as i64, colour);
                }
            }
        }
    }
    let to_px = |x: f64, z: f64| (((x - bx0 as f64) * scale as f64) as i64, ((z - bz0 as f64) * scale as f64) as i64);
    for pair in trajectory.steps.windows(2) {
        let colour = if pair[1].phase == Phase::Return { [230, 40, 200] } else { [255, 150, 20] };
        let (a, b) = (to_px(pair[0].state.feet[0], pair[0].state.feet[2]), to_px(pair[1].state.feet[0], pair[1].state.feet[2]));
        line(&mut img, w, h, a, b, colour);
    }
    for (i, c) in trajectory.waypoints.iter().enumerate() {
        let (px, py) = to_px(c[0] as f64 + 0.5, c[2] as f64 + 0.5);
        let (fill, r) = if i == 0 { ([255, 255, 255], 4) } else { ([0, 0, 0], 3) };
        for dy in -r..=r {
            for dx in -r..=r {
                put(&mut img, w, h, px + dx, py + dy, if dx.abs() == r || dy.abs() == r { [40, 40, 40] } else { fill });
            }
        }
    }
    (w, h, img)
}

fn put(img: &mut [u8], w: u32, h: u32, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < w && (y as u32) < h {
        let i = 3 * (y as usize * w as usize + x as usize);
        img[i..i + 3].copy_from_slice(&c);
    }
}

fn line(img: &mut [u8], w: u32, h: u32, a: (i64, i64), b: (i64, i64), c: [u8; 3]) {
    let n = (b.0 - a.0).abs().max((b.1 - a.1).abs()).max(1);
    for i in 0..=n {
        let x = a.0 + (b.0 - a.0) * i / n;
        let y = a.1 + (b.1 - a.1) * i / n;
        for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            put(img, w, h, x + dx, y + dy, c);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_pngs_round_trip_and_refuse_colour() {
        let depth: Vec<u16> = (0..12).map(|i| i * 5000 + 1).collect();
        let (back, w, h) = decode_depth_png16(&encode_depth_png16(4, 3, &depth)).unwrap();
        assert_eq!((back, w, h), (depth, 4, 3));
        let err = decode_depth_png16(&encode_png(2, 2, &[0; 12])).unwrap_err();
        assert!(err.contains("16-bit grayscale"), "{err}");
    }
}
