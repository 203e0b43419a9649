//! Reading a request: the JSON body, ids in the path, poses, actions and images,
//! each refused with a 4xx that names the field.

use axum::body::Bytes;
use axum::extract::Path;
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::http::{HeaderMap, StatusCode, header};
use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use memory::Pose;
use memory::input::PoseInput;
use motion::Action;
use serde::de::DeserializeOwned;
use serde_json::Value;

use crate::error::ApiError;
use crate::schemas::{MAX_COORDINATE, MAX_ID, MAX_TURN_DEG};
use super::Res;

/// A JSON body into `T`: 415 for another content type, 413 when too large,
/// 400 naming the field (`frames[0].pose.c2w.rotation`) when it does not fit.
pub(crate) fn parse<T: DeserializeOwned>(headers: &HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<T> {
    let json = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).is_some_and(|v| v.starts_with("application/json"));
    if !json {
        return Err(ApiError::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, "content-type", "send the body as application/json"));
    }
    let bytes = body.map_err(|r| ApiError::new(r.status(), "body", r.body_text()))?;
    let de = &mut serde_json::Deserializer::from_slice(&bytes);
    let first = match serde_path_to_error::deserialize(de) {
        Ok(v) => return Ok(v),
        Err(e) => e,
    };
    // Once more with whole-valued floats as integers; the first error names the field if that fails too.
    let retried = serde_json::from_slice::<Value>(&bytes).ok().and_then(|mut v| {
        integral_floats_as_integers(&mut v);
        serde_json::from_value(v).ok()
    });
    retried.ok_or_else(|| {
        let message = first.inner().to_string();
        let path = first.path().to_string();
        // A missing field is named itself, not the object it is missing from.
        let missing = message.strip_prefix("missing field `").and_then(|m| m.split('`').next());
        let field = match (path.as_str(), missing) {
            (".", Some(name)) => name.to_string(),
            (".", None) => "body".into(),
            (_, Some(name)) => format!("{path}.{name}"),
            (_, None) => path,
        };
        ApiError::bad(field, message)
    })
}

/// JSON has one number type and JSON Schema calls 7.0 an integer, so a
/// whole-valued float is taken where an integer is expected (a seed of
/// 7.0); fields that take floats accept integers anyway.
pub(crate) fn integral_floats_as_integers(v: &mut Value) {
    match v {
        Value::Number(n) if n.is_f64() => {
            let x = n.as_f64().unwrap_or(f64::NAN);
            if x.fract() == 0.0 && (0.0..1.8e19).contains(&x) {
                *v = Value::from(x as u64);
            } else if x.fract() == 0.0 && (-9.2e18..0.0).contains(&x) {
                *v = Value::from(x as i64);
            }
        }
        Value::Array(items) => items.iter_mut().for_each(integral_floats_as_integers),
        Value::Object(map) => map.values_mut().for_each(integral_floats_as_integers),
        _ => {}
    }
}

pub(crate) fn session_id(id: Result<Path<u64>, PathRejection>) -> Res<u64> {
    let id = id.map(|Path(id)| id).map_err(|_| ApiError::bad("session", format!("session ids are whole numbers from 0 to {MAX_ID}")))?;
    check_id("session", id)
}

/// Ids above [`MAX_ID`] are never handed out; the document's bound says so.
pub(crate) fn check_id(field: &str, id: u64) -> Res<u64> {
    if id > MAX_ID {
        return Err(ApiError::bad(field, format!("must be at most {MAX_ID}, got {id}")));
    }
    Ok(id)
}

/// A PNG (base64) as RGB bytes, width, height.
pub(crate) fn decode_png(field: &str, b64: &str) -> Res<(Vec<u8>, u32, u32)> {
    let bytes = B64.decode(b64.trim()).map_err(|e| ApiError::bad(field, format!("not base64: {e}")))?;
    world::picture::decode_rgb(&bytes).map_err(|e| ApiError::bad(field, e))
}

pub(crate) fn pose_from(input: &PoseInput, field: &str) -> Res<Pose> {
    let pose = input.resolve().map_err(|e| e.within(field))?;
    if pose.position().abs().max_element() > MAX_COORDINATE {
        return Err(ApiError::bad(format!("{field}.position"), format!("must lie within ±{MAX_COORDINATE:e} world units")));
    }
    Ok(pose)
}

/// Checks the action's angles; `at` is where it sits in the request (`action`, `candidates[0].actions[3]`).
pub(crate) fn validate_action(a: &Action, at: &str) -> Res<()> {
    for (field, v) in [("yaw_deg", a.yaw_deg), ("pitch_deg", a.pitch_deg)] {
        if !v.is_finite() || v.abs() > MAX_TURN_DEG {
            return Err(ApiError::bad(format!("{at}.{field}"), format!("must be a finite angle within ±{MAX_TURN_DEG} degrees, got {v}")));
        }
    }
    Ok(())
}

/// The sampler of a request that may name its sampler steps (1 to 1000; default: the server's `--steps`).
pub(crate) fn sampler(config: &crate::Config, m: &model::Model, steps: Option<usize>) -> Res<model::Sampler> {
    if steps.is_some_and(|n| !(1..=1000).contains(&n)) {
        return Err(ApiError::bad("steps", "must be from 1 to 1000"));
    }
    Ok(model::Sampler::new(&m.manifest().diffusion, steps.unwrap_or(config.steps), config.method, 0.0)?)
}
