//! Pinhole intrinsics in OpenCV's pixel convention, plus the near/far range
//! that truncates the view into a frustum.
//!
//! Pixel `(u, v)` with integer coordinates is the *centre* of a pixel; the
//! top-left pixel's centre is `(0, 0)`, so the image covers
//! `u ∈ [−0.5, width − 0.5]` and a centred principal point is `((W−1)/2, (H−1)/2)`.

use glam::{DVec2, DVec3};
use serde::{Deserialize, Serialize};

use crate::error::{InputError, check_finite};

/// Default near plane (blocks or metres).
pub const DEFAULT_NEAR: f64 = 0.1;
/// Default far plane: WorldMem's sampling radius.
pub const DEFAULT_FAR: f64 = 30.0;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    pub near: f64,
    pub far: f64,
}

impl Intrinsics {
    /// Builds and validates intrinsics with the default near/far.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32) -> Result<Self, InputError> {
        Intrinsics { fx, fy, cx, cy, width, height, near: DEFAULT_NEAR, far: DEFAULT_FAR }.validated()
    }

    /// Centred principal point and focal lengths from field-of-view angles in
    /// degrees. Without `vfov_deg` the pixels are square (`fy = fx`).
    pub fn from_fov(hfov_deg: f64, vfov_deg: Option<f64>, width: u32, height: u32) -> Result<Self, InputError> {
        check_dims(width, height)?;
        let fx = focal_from_fov("hfov_deg", hfov_deg, width)?;
        let fy = match vfov_deg {
            Some(v) => focal_from_fov("vfov_deg", v, height)?,
            None => fx,
        };
        Self::new(fx, fy, (width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0, width, height)
    }

    pub fn with_range(self, near: f64, far: f64) -> Result<Self, InputError> {
        Intrinsics { near, far, ..self }.validated()
    }

    /// Checks every field; the error names the first bad one.
    pub fn validated(self) -> Result<Self, InputError> {
        for (name, v) in [("fx", self.fx), ("fy", self.fy), ("cx", self.cx), ("cy", self.cy), ("near", self.near), ("far", self.far)]
        {
            check_finite(name, &[v])?;
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy), ("near", self.near)] {
            if v <= 0.0 {
                return Err(InputError::NotPositive { field: name.into(), value: v });
            }
        }
        check_dims(self.width, self.height)?;
        if self.near >= self.far {
            return Err(InputError::NearNotBeforeFar { near: self.near, far: self.far });
        }
        Ok(self)
    }

    /// Intrinsics for the same camera after resizing its image to
    /// `width × height`. Pixel centres map as `u' = (u + 0.5)·s − 0.5`, which
    /// is how `cv2.resize` samples.
    pub fn resized(&self, width: u32, height: u32) -> Result<Self, InputError> {
        check_dims(width, height)?;
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        Ok(Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
            width,
            height,
            ..*self
        })
    }

    /// Horizontal and vertical field of view in degrees (for a centred principal point).
    pub fn fov_deg(&self) -> (f64, f64) {
        let h = 2.0 * (self.width as f64 / (2.0 * self.fx)).atan();
        let v = 2.0 * (self.height as f64 / (2.0 * self.fy)).atan();
        (h.to_degrees(), v.to_degrees())
    }

    /// Projects a point in camera coordinates; `None` behind the camera.
    pub fn project(&self, p_cam: DVec3) -> Option<DVec2> {
        (p_cam.z > 0.0).then(|| DVec2::new(self.fx * p_cam.x / p_cam.z + self.cx, self.fy * p_cam.y / p_cam.z + self.cy))
    }

    /// The camera-frame point at `depth` (along the optical axis) seen at pixel `uv`.
    pub fn unproject(&self, uv: DVec2, depth: f64) -> DVec3 {
        DVec3::new((uv.x - self.cx) / self.fx * depth, (uv.y - self.cy) / self.fy * depth, depth)
    }

    /// The image rectangle's edges as slopes `x/z` and `y/z`:
    /// `(left, right, top, bottom)`.
    pub fn edge_slopes(&self) -> (f64, f64, f64, f64) {
        (
            (-0.5 - self.cx) / self.fx,
            (self.width as f64 - 0.5 - self.cx) / self.fx,
            (-0.5 - self.cy) / self.fy,
            (self.height as f64 - 0.5 - self.cy) / self.fy,
        )
    }
}

fn check_dims(width: u32, height: u32) -> Result<(), InputError> {
    if width == 0 {
        return Err(InputError::NotPositive { field: "width".into(), value: 0.0 });
    }
    if height == 0 {
        return Err(InputError::NotPositive { field: "height".into(), value: 0.0 });
    }
    Ok(())
}

fn focal_from_fov(field: &str, fov_deg: f64, pixels: u32) -> Result<f64, InputError> {
    check_finite(field, &[fov_deg])?;
    if fov_deg <= 0.0 || fov_deg >= 180.0 {
        return Err(InputError::FovOutOfRange { field: field.into(), value: fov_deg });
    }
    Ok(pixels as f64 / 2.0 / (fov_deg.to_radians() / 2.0).tan())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fov_round_trips_and_centres_the_principal_point() {
        let k = Intrinsics::from_fov(90.0, Some(60.0), 64, 48).unwrap();
        let (h, v) = k.fov_deg();
        assert!((h - 90.0).abs() < 1e-9 && (v - 60.0).abs() < 1e-9);
        assert_eq!((k.cx, k.cy), (31.5, 23.5));
        assert!((k.fx - 32.0).abs() < 1e-12);
    }

    #[test]
    fn image_edges_sit_half_a_pixel_outside_the_outer_centres() {
        let k = Intrinsics::from_fov(90.0, None, 64, 64).unwrap();
        let (l, r, t, b) = k.edge_slopes();
        assert!((l + 1.0).abs() < 1e-12 && (r - 1.0).abs() < 1e-12);
        assert!((t + 1.0).abs() < 1e-12 && (b - 1.0).abs() < 1e-12);
    }

    #[test]
    fn resizing_keeps_the_field_of_view_and_maps_pixel_centres() {
        let k = Intrinsics::new(100.0, 90.0, 63.5, 40.0, 128, 96).unwrap();
        let s = k.resized(64, 48).unwrap();
        let (h0, v0) = k.fov_deg();
        let (h1, v1) = s.fov_deg();
        assert!((h0 - h1).abs() < 1e-9 && (v0 - v1).abs() < 1e-9);
        let p = DVec3::new(0.3, -0.2, 2.0);
        let a = k.project(p).unwrap();
        let b = s.project(p).unwrap();
        assert!(((a.x + 0.5) * 0.5 - 0.5 - b.x).abs() < 1e-12);
        assert!(((a.y + 0.5) * 0.5 - 0.5 - b.y).abs() < 1e-12);
    }

    #[test]
    fn project_and_unproject_are_inverse() {
        let k = Intrinsics::new(50.0, 55.0, 30.0, 20.0, 64, 48).unwrap();
        let uv = DVec2::new(12.25, 40.5);
        assert!((k.project(k.unproject(uv, 3.0)).unwrap() - uv).length() < 1e-12);
        assert!(k.project(DVec3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn bad_intrinsics_name_their_field() {
        let field = |r: Result<Intrinsics, InputError>| r.unwrap_err().field().to_string();
        assert_eq!(field(Intrinsics::new(0.0, 1.0, 0.0, 0.0, 8, 8)), "fx");
        assert_eq!(field(Intrinsics::new(1.0, -2.0, 0.0, 0.0, 8, 8)), "fy");
        assert_eq!(field(Intrinsics::new(1.0, 1.0, f64::NAN, 0.0, 8, 8)), "cx");
        assert_eq!(field(Intrinsics::new(1.0, 1.0, 0.0, 0.0, 0, 8)), "width");
        assert_eq!(field(Intrinsics::from_fov(180.0, None, 8, 8)), "hfov_deg");
        assert_eq!(field(Intrinsics::from_fov(90.0, Some(0.0), 8, 8)), "vfov_deg");
        assert_eq!(field(Intrinsics::from_fov(f64::INFINITY, None, 8, 8)), "hfov_deg");
        let k = Intrinsics::from_fov(90.0, None, 8, 8).unwrap();
        assert!(matches!(k.with_range(5.0, 5.0), Err(InputError::NearNotBeforeFar { .. })));
        assert_eq!(field(k.with_range(0.0, 5.0)), "near");
        assert_eq!(field(k.with_range(0.1, f64::INFINITY)), "far");
    }
}
