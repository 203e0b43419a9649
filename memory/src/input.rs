//! Poses and intrinsics as users write them in JSON (the CLI's `geometry`
//! requests and the REST API share these forms). `resolve` checks them and
//! names the offending field.

use serde::Deserialize;

use crate::{AngleUnit, InputError, Intrinsics, Pose, Pose5, Pose5Convention};

/// A pose in any supported convention (exactly one key).
#[derive(Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum PoseInput {
    /// Canonical: OpenCV camera-to-world, row-major rotation.
    C2w { rotation: [[f64; 3]; 3], position: [f64; 3] },
    /// OpenCV extrinsics (world-to-camera), as `cv2.solvePnP` returns.
    Opencv { rvec: [f64; 3], tvec: [f64; 3] },
    /// OpenGL/Blender camera-to-world 4×4, row-major.
    Opengl([[f64; 4]; 4]),
    /// A 5-D pose in a named convention and unit.
    Pose5 {
        x: f64,
        y: f64,
        z: f64,
        pitch: f64,
        yaw: f64,
        convention: Pose5Convention,
        unit: AngleUnit,
    },
}

impl PoseInput {
    pub fn resolve(&self) -> Result<Pose, InputError> {
        match self {
            PoseInput::C2w { rotation, position } => Pose::from_rows(*rotation, *position),
            PoseInput::Opencv { rvec, tvec } => Pose::from_opencv_extrinsics(*rvec, *tvec),
            PoseInput::Opengl(m) => Pose::from_opengl(*m),
            PoseInput::Pose5 { x, y, z, pitch, yaw, convention, unit } => {
                Pose::from_pose5(&Pose5 { x: *x, y: *y, z: *z, pitch: *pitch, yaw: *yaw }, *convention, *unit)
            }
        }
    }
}

/// Intrinsics as focal lengths (`fx`, optional `fy`, `cx`, `cy`) or as
/// field-of-view angles (`hfov_deg`, optional `vfov_deg`); principal point
/// defaults to the image centre and `near`/`far` to 0.1/30.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsInput {
    fx: Option<f64>,
    fy: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    hfov_deg: Option<f64>,
    vfov_deg: Option<f64>,
    width: u32,
    height: u32,
    near: Option<f64>,
    far: Option<f64>,
}

impl IntrinsicsInput {
    pub fn resolve(&self) -> Result<Intrinsics, InputError> {
        let base = match (self.fx, self.hfov_deg) {
            (Some(_), Some(_)) => return Err(InputError::Invalid { field: "hfov_deg".into(), reason: "give either fx or hfov_deg, not both".into() }),
            (None, None) => return Err(InputError::Invalid { field: "fx".into(), reason: "give fx (focal length in pixels) or hfov_deg".into() }),
            (Some(fx), None) => {
                if self.vfov_deg.is_some() {
                    return Err(InputError::Invalid { field: "vfov_deg".into(), reason: "only valid together with hfov_deg".into() });
                }
                let centre = |n: u32| (n as f64 - 1.0) / 2.0;
                Intrinsics::new(
                    fx,
                    self.fy.unwrap_or(fx),
                    self.cx.unwrap_or(centre(self.width)),
                    self.cy.unwrap_or(centre(self.height)),
                    self.width,
                    self.height,
                )?
            }
            (None, Some(h)) => {
                for (field, v) in [("fy", self.fy), ("cx", self.cx), ("cy", self.cy)] {
                    if v.is_some() {
                        return Err(InputError::Invalid { field: field.into(), reason: "only valid together with fx".into() });
                    }
                }
                Intrinsics::from_fov(h, self.vfov_deg, self.width, self.height)?
            }
        };
        base.with_range(self.near.unwrap_or(base.near), self.far.unwrap_or(base.far))
    }
}

