//! Ray casting through the voxel grid with the project's OpenCV camera:
//! RGB (u8) and metric depth (z along the optical axis, f32).

use glam::{DVec2, DVec3};
use memory::{Intrinsics, Pose};

use crate::blocks::{Block, Face};
use crate::noise::smoothstep;
use crate::terrain::{HEIGHT, World};

/// What the renderer draws beyond the geometry.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct RenderSettings {
    /// Rays stop after this Euclidean distance (blocks); beyond is sky.
    pub view_distance: f64,
    /// Fog starts at this distance and hides everything by `view_distance`.
    pub fog_start: f64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings { view_distance: 48.0, fog_start: 20.0 }
    }
}

/// One rendered view, row-major from the top-left pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// `height × width × 3`, sRGB-ish u8.
    pub rgb: Vec<u8>,
    /// `height × width`, camera-space z of the surface seen at each pixel
    /// centre; `f32::INFINITY` where the ray sees sky.
    pub depth: Vec<f32>,
}

/// Where a ray met a block.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Ray parameter: for a ray `o + t·d` with `d` the camera-frame direction
    /// `((u−cx)/fx, (v−cy)/fy, 1)` turned into the world, `t` is the camera z.
    pub t: f64,
    pub cell: [i32; 3],
    pub block: Block,
    pub face: Face,
    pub point: DVec3,
}

/// Walks the grid cells along `origin + t·dir` (Amanatides & Woo) up to
/// `t_max` and returns the first solid one. `dir` need not be unit length.
pub fn cast(world: &World, origin: DVec3, dir: DVec3, t_max: f64) -> Option<Hit> {
    let mut cell = [origin.x.floor() as i32, origin.y.floor() as i32, origin.z.floor() as i32];
    let o = origin.to_array();
    let d = dir.to_array();
    let mut step = [0i32; 3];
    let mut t_next = [f64::INFINITY; 3];
    let mut t_delta = [f64::INFINITY; 3];
    for a in 0..3 {
        if d[a] > 0.0 {
            step[a] = 1;
            t_next[a] = ((cell[a] + 1) as f64 - o[a]) / d[a];
            t_delta[a] = 1.0 / d[a];
        } else if d[a] < 0.0 {
            step[a] = -1;
            t_next[a] = (cell[a] as f64 - o[a]) / d[a];
            t_delta[a] = -1.0 / d[a];
        }
    }
    let (mut t, mut axis) = (0.0, 1usize);
    loop {
        let code = world.code(cell[0], cell[1], cell[2]);
        if code != 0 {
            let face = match axis {
                0 => Face::SideX,
                2 => Face::SideZ,
                _ if step[1] > 0 => Face::Bottom,
                _ => Face::Top,
            };
            return Some(Hit { t, cell, block: Block::from_u8(code), face, point: origin + dir * t });
        }
        axis = if t_next[0] < t_next[1] {
            if t_next[0] < t_next[2] { 0 } else { 2 }
        } else if t_next[1] < t_next[2] {
            1
        } else {
            2
        };
        t = t_next[axis];
        if t > t_max {
            return None;
        }
        // Leaving the world upward or below the floor: nothing more to hit.
        if (cell[1] >= HEIGHT && step[1] >= 0) || (cell[1] < 0 && step[1] <= 0) {
            return None;
        }
        cell[axis] += step[axis];
        t_next[axis] += t_delta[axis];
    }
}

/// Renders the view from `pose` (OpenCV camera-to-world, in world blocks).
pub fn render(world: &World, pose: &Pose, k: &Intrinsics, settings: &RenderSettings) -> Frame {
    let (w, h) = (k.width, k.height);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    let mut depth = vec![f32::INFINITY; (w * h) as usize];
    let rot = pose.rotation();
    let origin = pose.position();
    for v in 0..h {
        for u in 0..w {
            let dir = rot * k.unproject(DVec2::new(u as f64, v as f64), 1.0);
            let len = dir.length();
            let i = (v * w + u) as usize;
            let sky = sky_colour(dir.y / len);
            let colour = match cast(world, origin, dir, settings.view_distance / len) {
                Some(hit) => {
                    depth[i] = hit.t as f32;
                    let lit = shade(&hit);
                    let fog = smoothstep(settings.fog_start, settings.view_distance, hit.t * len);
                    [0, 1, 2].map(|c| lit[c] * (1.0 - fog) + sky[c] * fog)
                }
                None => sky,
            };
            for c in 0..3 {
                rgb[3 * i + c] = colour[c].round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    Frame { width: w, height: h, rgb, depth }
}

/// Texel colour times a fixed light per face direction, as Minecraft does.
fn shade(hit: &Hit) -> [f64; 3] {
    let frac = |v: f64| v - v.floor();
    let p = hit.point;
    let (fu, fv) = match hit.face {
        Face::Top | Face::Bottom => (frac(p.x), frac(p.z)),
        Face::SideX => (frac(p.z), 1.0 - frac(p.y)),
        Face::SideZ => (frac(p.x), 1.0 - frac(p.y)),
    };
    let texel = |f: f64| ((f * 8.0) as u32).min(7);
    let colour = hit.block.texel(hit.face, hit.cell, texel(fu), texel(fv));
    let light = match (hit.block, hit.face) {
        (Block::Glowstone, _) => 1.0,
        (_, Face::Top) => 1.0,
        (_, Face::SideX) => 0.8,
        (_, Face::SideZ) => 0.65,
        (_, Face::Bottom) => 0.5,
    };
    colour.map(|c| c * light)
}

/// Horizon-to-zenith gradient by the ray's elevation sine.
fn sky_colour(elevation: f64) -> [f64; 3] {
    let t = elevation.clamp(0.0, 1.0).sqrt();
    let (horizon, zenith) = ([196.0, 218.0, 240.0], [92.0, 142.0, 222.0]);
    [0, 1, 2].map(|c| horizon[c] + (zenith[c] - horizon[c]) * t)
}
