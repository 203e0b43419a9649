//! Camera poses and the conversions between the conventions users bring.
//!
//! The canonical pose is **camera-to-world in the OpenCV camera frame**
//! (x right, y down, z forward): `p_world = rotation * p_cam + position`.
//! Every other convention is an explicit conversion to and from it; the axes
//! and signs of each are tabulated in `docs/conventions.md`.

use glam::{DMat3, DMat4, DVec3, DVec4};
use serde::{Deserialize, Serialize};

use crate::error::{InputError, check_finite};

/// How far `RᵀR` may stray from the identity before a matrix is refused.
const ORTHONORMAL_TOLERANCE: f64 = 1e-6;

/// A rigid camera-to-world transform, camera axes as in OpenCV.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    rotation: DMat3,
    position: DVec3,
}

impl Pose {
    /// Builds a pose, refusing non-finite values and matrices that are not
    /// proper rotations (orthonormal with determinant +1).
    pub fn new(rotation: DMat3, position: DVec3) -> Result<Self, InputError> {
        check_finite("rotation", &rotation.to_cols_array())?;
        check_finite("position", &position.to_array())?;
        check_rotation("rotation", &rotation)?;
        Ok(Pose { rotation, position })
    }

    /// A pose at `position` with the identity rotation (looking along world +z).
    pub fn from_position(position: DVec3) -> Self {
        Pose { rotation: DMat3::IDENTITY, position }
    }

    /// Row-major 3×3 rotation and position, as JSON users write them.
    pub fn from_rows(rotation: [[f64; 3]; 3], position: [f64; 3]) -> Result<Self, InputError> {
        let r = DMat3::from_cols_array_2d(&rotation).transpose();
        Self::new(r, DVec3::from_array(position))
    }

    pub fn rotation(&self) -> DMat3 {
        self.rotation
    }

    /// The camera centre in world coordinates.
    pub fn position(&self) -> DVec3 {
        self.position
    }

    /// The optical axis (camera +z) in world coordinates.
    pub fn forward(&self) -> DVec3 {
        self.rotation.z_axis
    }

    pub fn rotation_rows(&self) -> [[f64; 3]; 3] {
        self.rotation.transpose().to_cols_array_2d()
    }

    pub fn camera_to_world(&self, p_cam: DVec3) -> DVec3 {
        self.rotation * p_cam + self.position
    }

    pub fn world_to_camera(&self, p_world: DVec3) -> DVec3 {
        self.rotation.transpose() * (p_world - self.position)
    }

    /// `self⁻¹ · other`: `other` expressed in this camera's frame.
    pub fn relative_to(&self, reference: &Pose) -> Pose {
        let rt = reference.rotation.transpose();
        Pose { rotation: rt * self.rotation, position: rt * (self.position - reference.position) }
    }

    /// The inverse of [`Pose::matrix_rows`]: a row-major 4×4 camera-to-world
    /// matrix (the last row is ignored).
    pub fn from_matrix_rows(m: [[f64; 4]; 4]) -> Result<Self, InputError> {
        let r = |i: usize| [m[i][0], m[i][1], m[i][2]];
        Self::from_rows([r(0), r(1), r(2)], [m[0][3], m[1][3], m[2][3]])
    }

    /// 4×4 camera-to-world matrix, row-major.
    pub fn matrix_rows(&self) -> [[f64; 4]; 4] {
        let m = DMat4::from_cols(
            self.rotation.x_axis.extend(0.0),
            self.rotation.y_axis.extend(0.0),
            self.rotation.z_axis.extend(0.0),
            self.position.extend(1.0),
        );
        m.transpose().to_cols_array_2d()
    }

    // ----- OpenCV extrinsics -------------------------------------------------

    /// From OpenCV extrinsics: `rvec` (Rodrigues axis·angle) and `tvec` map
    /// world to camera, `p_cam = R(rvec)·p_world + tvec`, as `cv2.solvePnP`
    /// returns and `cv2.projectPoints` takes.
    pub fn from_opencv_extrinsics(rvec: [f64; 3], tvec: [f64; 3]) -> Result<Self, InputError> {
        check_finite("rvec", &rvec)?;
        check_finite("tvec", &tvec)?;
        let r_wc = rodrigues(DVec3::from_array(rvec));
        let r_cw = r_wc.transpose();
        let position = -(r_cw * DVec3::from_array(tvec));
        // Finite inputs can still overflow: |rvec| beyond f64 makes a NaN rotation, a huge tvec an infinite centre.
        if !r_cw.is_finite() {
            return Err(InputError::invalid("rvec", "too large: the rotation it makes overflows"));
        }
        if !position.is_finite() {
            return Err(InputError::invalid("tvec", "too large: the camera centre it makes overflows"));
        }
        Ok(Pose { rotation: r_cw, position })
    }

    /// The inverse of [`Pose::from_opencv_extrinsics`]; the angle of `rvec` is in `[0, π]`.
    pub fn to_opencv_extrinsics(&self) -> ([f64; 3], [f64; 3]) {
        let r_wc = self.rotation.transpose();
        let tvec = -(r_wc * self.position);
        (rodrigues_inverse(&r_wc).to_array(), tvec.to_array())
    }

    // ----- OpenGL / Blender ---------------------------------------------------

    /// From an OpenGL/Blender camera-to-world matrix (camera x right, y up,
    /// looking down −z), row-major 4×4 with last row `0 0 0 1`.
    pub fn from_opengl(matrix: [[f64; 4]; 4]) -> Result<Self, InputError> {
        for (i, row) in matrix.iter().enumerate() {
            check_finite(&format!("matrix[{i}]"), row)?;
        }
        let m = DMat4::from_cols_array_2d(&matrix).transpose();
        if (m.row(3) - DVec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > 1e-9 {
            return Err(InputError::invalid("matrix", "last row must be [0, 0, 0, 1]"));
        }
        let r_gl = DMat3::from_mat4(m);
        check_rotation("matrix", &r_gl)?;
        Ok(Pose { rotation: r_gl * GL_FROM_CV, position: m.w_axis.truncate() })
    }

    /// Row-major OpenGL/Blender camera-to-world matrix.
    pub fn to_opengl(&self) -> [[f64; 4]; 4] {
        Pose { rotation: self.rotation * GL_FROM_CV, position: self.position }.matrix_rows()
    }

    // ----- 5-D (x, y, z, pitch, yaw) poses ------------------------------------

    /// From a 5-D pose in one of the Minecraft-family conventions.
    pub fn from_pose5(p: &Pose5, convention: Pose5Convention, unit: AngleUnit) -> Result<Self, InputError> {
        check_finite("x", &[p.x])?;
        check_finite("y", &[p.y])?;
        check_finite("z", &[p.z])?;
        check_finite("pitch", &[p.pitch])?;
        check_finite("yaw", &[p.yaw])?;
        let (pitch, yaw) = (unit.to_radians(p.pitch), unit.to_radians(p.yaw));
        let position = DVec3::new(p.x, p.y, p.z);
        let rotation = match convention {
            Pose5Convention::Minecraft => notchian_rotation(pitch, yaw),
            Pose5Convention::Mineflayer => notchian_rotation(-pitch, std::f64::consts::PI - yaw),
            Pose5Convention::WorldMem => {
                // WorldMem's camera-to-world is R_y(yaw)·R_x(pitch) on a camera
                // with x left, y up, z forward; flipping x and y gives OpenCV's.
                DMat3::from_rotation_y(yaw) * DMat3::from_rotation_x(pitch) * WORLDMEM_FROM_CV
            }
        };
        Ok(Pose { rotation, position })
    }

    /// To a 5-D pose. Fails when the camera is rolled (its x axis leaves the
    /// horizontal plane), which five numbers cannot represent. Yaw is wrapped
    /// into (−180°, 180°]; pitch lies in [−90°, 90°].
    pub fn to_pose5(&self, convention: Pose5Convention, unit: AngleUnit) -> Result<Pose5, InputError> {
        let right = self.rotation.x_axis;
        let forward = self.rotation.z_axis;
        if right.y.abs() > 1e-6 {
            return Err(InputError::invalid(
                "rotation",
                format!("camera is rolled (x axis has world-y component {:.3e}); a 5-D pose has no roll", right.y),
            ));
        }
        // Notchian angles: right = (−cos yaw, 0, −sin yaw) holds at every pitch,
        // so yaw stays defined when looking straight up or down.
        let yaw_n = (-right.z).atan2(-right.x);
        let pitch_n = (-forward.y).atan2(forward.x.hypot(forward.z));
        let (pitch, yaw) = match convention {
            Pose5Convention::Minecraft => (pitch_n, yaw_n),
            Pose5Convention::Mineflayer => (-pitch_n, std::f64::consts::PI - yaw_n),
            Pose5Convention::WorldMem => (pitch_n, -yaw_n),
        };
        Ok(Pose5 {
            x: self.position.x,
            y: self.position.y,
            z: self.position.z,
            pitch: unit.from_radians(pitch),
            yaw: unit.from_radians(wrap_pi(yaw)),
        })
    }
}

/// OpenGL camera axes expressed in OpenCV's: flip y and z.
const GL_FROM_CV: DMat3 = DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));
/// WorldMem camera axes (x left, y up, z forward) expressed in OpenCV's: flip x and y.
const WORLDMEM_FROM_CV: DMat3 = DMat3::from_diagonal(DVec3::new(-1.0, -1.0, 1.0));

/// `(x, y, z, pitch, yaw)` as recorded by Minecraft-like worlds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose5 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub pitch: f64,
    pub yaw: f64,
}

/// The 5-D conventions in the wild. All share Minecraft's world axes:
/// x east, y up, z south (right-handed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Pose5Convention {
    /// The game's own (F3 screen): yaw 0 faces +z (south), 90° faces −x
    /// (west); positive pitch looks down. Usually in degrees.
    Minecraft,
    /// mineflayer, as LoopNav records it: yaw 0 faces −z (north), π/2 faces
    /// −x (west); positive pitch looks up. Usually in radians.
    /// `yaw = π − yaw_minecraft`, `pitch = −pitch_minecraft`.
    Mineflayer,
    /// WorldMem's camera matrix `R_y(yaw)·R_x(pitch)`: yaw 0 faces +z, 90°
    /// faces +x (east); positive pitch looks down. Degrees.
    /// `yaw = −yaw_minecraft`, `pitch = pitch_minecraft`. (WorldMem's own FoV
    /// test reads positive pitch as up; see `docs/conventions.md`.)
    #[serde(rename = "worldmem")]
    WorldMem,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AngleUnit {
    Degrees,
    Radians,
}

impl AngleUnit {
    fn to_radians(self, a: f64) -> f64 {
        match self {
            AngleUnit::Degrees => a.to_radians(),
            AngleUnit::Radians => a,
        }
    }

    #[allow(clippy::wrong_self_convention)] // the unit is the target of the conversion, as `to_radians`'s is its source
    fn from_radians(self, a: f64) -> f64 {
        match self {
            AngleUnit::Degrees => a.to_degrees(),
            AngleUnit::Radians => a,
        }
    }
}

/// Camera-to-world rotation for Notchian pitch/yaw (radians): columns are the
/// camera's right, down and forward axes in the world.
fn notchian_rotation(pitch: f64, yaw: f64) -> DMat3 {
    let (sp, cp) = pitch.sin_cos();
    let (sy, cy) = yaw.sin_cos();
    let forward = DVec3::new(-sy * cp, -sp, cy * cp);
    let right = DVec3::new(-cy, 0.0, -sy);
    let down = forward.cross(right);
    DMat3::from_cols(right, down, forward)
}

fn wrap_pi(a: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let w = (a + PI).rem_euclid(TAU) - PI;
    if w <= -PI + 1e-15 { w + TAU } else { w }
}

/// Refuses anything but a proper rotation, naming `field`.
pub(crate) fn check_rotation(field: &str, r: &DMat3) -> Result<(), InputError> {
    let err = (r.transpose() * *r - DMat3::IDENTITY).to_cols_array().iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if err > ORTHONORMAL_TOLERANCE {
        return Err(InputError::NotARotation {
            field: field.to_string(),
            reason: format!("not orthonormal (max |RᵀR − I| = {err:.2e}, tolerance {ORTHONORMAL_TOLERANCE:.0e})"),
        });
    }
    if r.determinant() < 0.0 {
        return Err(InputError::NotARotation {
            field: field.to_string(),
            reason: "determinant is −1 (a reflection: check the handedness of your axes)".into(),
        });
    }
    Ok(())
}

/// Rodrigues' formula: axis·angle vector to rotation matrix.
pub fn rodrigues(rvec: DVec3) -> DMat3 {
    let theta = rvec.length();
    if theta < 1e-12 {
        // First order: I + [r]×, exact enough below 1e-12 rad.
        return DMat3::IDENTITY + skew(rvec);
    }
    DMat3::from_axis_angle(rvec / theta, theta)
}

/// Rotation matrix to axis·angle, angle in `[0, π]`.
pub fn rodrigues_inverse(r: &DMat3) -> DVec3 {
    let q = glam::DQuat::from_mat3(r).normalize();
    // Keep the angle in [0, π] by choosing the quaternion with w ≥ 0.
    let q = if q.w < 0.0 { -q } else { q };
    let (axis, angle) = q.to_axis_angle();
    axis * angle
}

fn skew(v: DVec3) -> DMat3 {
    DMat3::from_cols(DVec3::new(0.0, v.z, -v.y), DVec3::new(-v.z, 0.0, v.x), DVec3::new(v.y, -v.x, 0.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: DMat3, b: DMat3, tol: f64) -> bool {
        (a - b).to_cols_array().iter().all(|v| v.abs() < tol)
    }

    #[test]
    fn minecraft_axes_at_zero_and_quarter_turns() {
        let p = |pitch, yaw| {
            Pose::from_pose5(&Pose5 { x: 0.0, y: 0.0, z: 0.0, pitch, yaw }, Pose5Convention::Minecraft, AngleUnit::Degrees)
                .unwrap()
        };
        let south = p(0.0, 0.0);
        assert!((south.forward() - DVec3::Z).length() < 1e-12);
        // Facing south with y up, the camera's right hand points west (−x).
        assert!((south.rotation().x_axis - DVec3::NEG_X).length() < 1e-12);
        assert!((south.rotation().y_axis - DVec3::NEG_Y).length() < 1e-12);
        assert!((p(0.0, 90.0).forward() - DVec3::NEG_X).length() < 1e-12);
        assert!((p(0.0, 180.0).forward() - DVec3::NEG_Z).length() < 1e-12);
        assert!((p(0.0, -90.0).forward() - DVec3::X).length() < 1e-12);
        assert!((p(90.0, 0.0).forward() - DVec3::NEG_Y).length() < 1e-12, "positive pitch looks down");
    }

    #[test]
    fn mineflayer_and_worldmem_agree_with_their_documented_relations() {
        for &(pitch, yaw) in &[(0.0, 0.0), (12.0, 33.0), (-40.0, 170.0), (89.0, -120.0)] {
            let mc = Pose5 { x: 1.0, y: 2.0, z: 3.0, pitch, yaw };
            let reference = Pose::from_pose5(&mc, Pose5Convention::Minecraft, AngleUnit::Degrees).unwrap();
            let mf = Pose5 { pitch: -pitch.to_radians(), yaw: std::f64::consts::PI - yaw.to_radians(), ..mc };
            let from_mf = Pose::from_pose5(&mf, Pose5Convention::Mineflayer, AngleUnit::Radians).unwrap();
            let wm = Pose5 { pitch, yaw: -yaw, ..mc };
            let from_wm = Pose::from_pose5(&wm, Pose5Convention::WorldMem, AngleUnit::Degrees).unwrap();
            assert!(close(reference.rotation(), from_mf.rotation(), 1e-12));
            assert!(close(reference.rotation(), from_wm.rotation(), 1e-12));
        }
    }

    #[test]
    fn pose5_round_trips_in_every_convention_and_unit() {
        for conv in [Pose5Convention::Minecraft, Pose5Convention::Mineflayer, Pose5Convention::WorldMem] {
            for unit in [AngleUnit::Degrees, AngleUnit::Radians] {
                let k = if unit == AngleUnit::Degrees { 1.0 } else { 1f64.to_radians() };
                let p = Pose5 { x: -4.0, y: 70.5, z: 12.25, pitch: 37.0 * k, yaw: -151.0 * k };
                let back = Pose::from_pose5(&p, conv, unit).unwrap().to_pose5(conv, unit).unwrap();
                assert!((back.pitch - p.pitch).abs() < 1e-9 && (back.yaw - p.yaw).abs() < 1e-9, "{conv:?} {unit:?}: {back:?}");
            }
        }
    }

    #[test]
    fn yaw_survives_looking_straight_down() {
        let p = Pose5 { x: 0.0, y: 0.0, z: 0.0, pitch: 90.0, yaw: 30.0 };
        let back = Pose::from_pose5(&p, Pose5Convention::Minecraft, AngleUnit::Degrees)
            .unwrap()
            .to_pose5(Pose5Convention::Minecraft, AngleUnit::Degrees)
            .unwrap();
        assert!((back.yaw - 30.0).abs() < 1e-9 && (back.pitch - 90.0).abs() < 1e-9);
    }

    #[test]
    fn rolled_camera_has_no_5d_pose() {
        let rolled = Pose::new(DMat3::from_rotation_z(0.3), DVec3::ZERO).unwrap();
        let err = rolled.to_pose5(Pose5Convention::Minecraft, AngleUnit::Degrees).unwrap_err();
        assert_eq!(err.field(), "rotation");
    }

    #[test]
    fn opencv_extrinsics_round_trip() {
        let pose = Pose::new(DMat3::from_euler(glam::EulerRot::YXZ, 0.4, -0.2, 2.9), DVec3::new(3.0, -1.0, 7.0)).unwrap();
        let (rvec, tvec) = pose.to_opencv_extrinsics();
        let back = Pose::from_opencv_extrinsics(rvec, tvec).unwrap();
        assert!(close(pose.rotation(), back.rotation(), 1e-12));
        assert!((pose.position() - back.position()).length() < 1e-12);
        // World-to-camera of the extrinsics equals the inverse pose.
        let p = DVec3::new(0.3, 2.0, -5.0);
        let via_ext = rodrigues(DVec3::from_array(rvec)) * p + DVec3::from_array(tvec);
        assert!((via_ext - pose.world_to_camera(p)).length() < 1e-12);
    }

    #[test]
    fn extrinsics_that_overflow_are_refused_by_name() {
        // Finite inputs, found by schemathesis: |rvec| overflows to infinity and the rotation turns NaN.
        let err = Pose::from_opencv_extrinsics([0.0, 1.7976931348623157e308, 1.7976931348623157e308], [0.0; 3]).unwrap_err();
        assert_eq!(err.field(), "rvec");
        let err = Pose::from_opencv_extrinsics([0.0, std::f64::consts::FRAC_PI_4, 0.0], [1.7e308, 0.0, 1.7e308]).unwrap_err();
        assert_eq!(err.field(), "tvec", "{err}");
        assert!(Pose::from_opencv_extrinsics([1e26, -3.0, 0.5], [1e9, 0.0, -1e9]).is_ok(), "large but representable is a pose");
    }

    #[test]
    fn rodrigues_handles_zero_and_half_turn() {
        assert!(rodrigues_inverse(&DMat3::IDENTITY).length() < 1e-12);
        let half = DMat3::from_rotation_y(std::f64::consts::PI);
        let r = rodrigues_inverse(&half);
        assert!((r.length() - std::f64::consts::PI).abs() < 1e-9);
        assert!(close(rodrigues(r), half, 1e-9));
    }

    #[test]
    fn opengl_flips_y_and_z() {
        let pose = Pose::new(DMat3::from_rotation_y(0.7), DVec3::new(1.0, 2.0, 3.0)).unwrap();
        let gl = pose.to_opengl();
        let back = Pose::from_opengl(gl).unwrap();
        assert!(close(pose.rotation(), back.rotation(), 1e-12));
        // The OpenGL camera looks down its −z: that must be OpenCV's +z.
        let gl_forward = -DVec3::new(gl[0][2], gl[1][2], gl[2][2]);
        assert!((gl_forward - pose.forward()).length() < 1e-12);
    }

    #[test]
    fn bad_rotations_are_refused_with_the_field_name() {
        let scaled = DMat3::from_diagonal(DVec3::new(1.0, 1.0, 1.1));
        assert!(matches!(Pose::new(scaled, DVec3::ZERO), Err(InputError::NotARotation { .. })));
        let mirror = DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0));
        let err = Pose::new(mirror, DVec3::ZERO).unwrap_err();
        assert!(err.to_string().contains("reflection"), "{err}");
        let err = Pose::new(DMat3::IDENTITY, DVec3::new(f64::NAN, 0.0, 0.0)).unwrap_err();
        assert_eq!(err.field(), "position[0]");
        let err = Pose::from_opencv_extrinsics([0.0, f64::INFINITY, 0.0], [0.0; 3]).unwrap_err();
        assert_eq!(err.field(), "rvec[1]");
        let p = Pose5 { x: 0.0, y: 0.0, z: 0.0, pitch: f64::NAN, yaw: 0.0 };
        assert_eq!(Pose::from_pose5(&p, Pose5Convention::Minecraft, AngleUnit::Degrees).unwrap_err().field(), "pitch");
    }
}
