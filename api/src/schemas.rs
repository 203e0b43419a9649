//! JSON Schema for the request fields whose types other crates own (a pose
//! in its four forms, intrinsics, a policy, an action, a biome), with the
//! bounds the server checks, for the OpenAPI document and the request types'
//! annotations; tested against those crates' own parsers.

use serde_json::{Value, json};
use utoipa::openapi::schema::{Object, OneOfBuilder, Schema, Type};
use utoipa::openapi::{Ref, RefOr};

/// The largest id a path accepts: ids are u64, and JSON Schema tools
/// handle integers up to i64 safely.
pub const MAX_ID: u64 = i64::MAX as u64;
/// Angles of an action, in degrees either way.
pub const MAX_TURN_DEG: f64 = 180.0;
/// Pose coordinates, in world units either way (beyond it the f64 geometry has no centimetres left).
pub const MAX_COORDINATE: f64 = 1e9;

/// An optional field of a foreign type: the type, or null (taken as absent).
fn nullable(name: &str) -> RefOr<Schema> {
    RefOr::T(Schema::OneOf(OneOfBuilder::new().item(Ref::from_schema_name(name)).item(Object::with_type(Type::Null)).build()))
}

/// An optional list of a foreign type: an array of it, or null.
fn nullable_list(name: &str) -> RefOr<Schema> {
    let list = utoipa::openapi::schema::Array::new(Ref::from_schema_name(name));
    RefOr::T(Schema::OneOf(OneOfBuilder::new().item(list).item(Object::with_type(Type::Null)).build()))
}

pub fn optional_actions() -> RefOr<Schema> {
    nullable_list("Action")
}
pub fn optional_poses() -> RefOr<Schema> {
    nullable_list("Pose")
}
pub fn optional_pose() -> RefOr<Schema> {
    nullable("Pose")
}
pub fn optional_intrinsics() -> RefOr<Schema> {
    nullable("IntrinsicsInput")
}
pub fn optional_action() -> RefOr<Schema> {
    nullable("Action")
}
pub fn optional_policy() -> RefOr<Schema> {
    nullable("PolicySpec")
}
pub fn optional_biome() -> RefOr<Schema> {
    nullable("Biome")
}

pub fn action() -> Ref {
    Ref::from_schema_name("Action")
}
pub fn pose_ref() -> Ref {
    Ref::from_schema_name("Pose")
}
pub fn camera_ref() -> Ref {
    Ref::from_schema_name("Intrinsics")
}
pub fn optional_covisibility() -> RefOr<Schema> {
    nullable("CoVisibility")
}
pub fn resolved_policy_ref() -> Ref {
    Ref::from_schema_name("Policy")
}

fn vector(n: usize, bound: Option<f64>) -> Value {
    let mut item = json!({ "type": "number" });
    if let Some(b) = bound {
        item = json!({ "type": "number", "minimum": -b, "maximum": b });
    }
    json!({ "type": "array", "items": item, "minItems": n, "maxItems": n })
}

fn matrix(rows: usize, columns: usize) -> Value {
    json!({ "type": "array", "items": vector(columns, None), "minItems": rows, "maxItems": rows })
}

fn one_key(key: &str, description: &str, value: Value) -> Value {
    json!({ "type": "object", "description": description, "required": [key], "properties": { key: value }, "additionalProperties": false })
}

/// (name, schema) of every type the routes take from other crates.
pub(crate) fn foreign_schemas() -> Vec<(&'static str, Value)> {
    use memory::CoVisibility;
    use memory::PolicyKind::*;
    let d = CoVisibility::default();
    let kinds: Vec<&str> = [Baseline, NearestFramePacking, MemoryRetrieval, WorldPack, WorldMemGreedy].map(|k| k.name()).to_vec();
    vec![
        (
            "Pose",
            json!({
                "description": "A camera pose in one of four forms (exactly one key). The canonical form is OpenCV camera-to-world \
                                (x right, y down, z forward); `c2w.rotation` and the 3×3 part of `opengl` must be rotations \
                                (orthonormal, determinant +1), which JSON Schema cannot state; the server answers 400 otherwise. \
                                Positions lie within ±1e9 world units.",
                "oneOf": [
                    one_key("c2w", "OpenCV camera-to-world: row-major rotation and the camera centre",
                        json!({ "type": "object", "required": ["rotation", "position"], "additionalProperties": false,
                                "properties": { "rotation": matrix(3, 3), "position": vector(3, Some(MAX_COORDINATE)) } })),
                    one_key("opencv", "OpenCV extrinsics (world-to-camera), as cv2.solvePnP returns: a Rodrigues vector and a translation",
                        json!({ "type": "object", "required": ["rvec", "tvec"], "additionalProperties": false,
                                "properties": { "rvec": vector(3, None), "tvec": vector(3, Some(MAX_COORDINATE)) } })),
                    one_key("opengl", "OpenGL/Blender camera-to-world 4×4, row-major (last row 0, 0, 0, 1)", matrix(4, 4)),
                    one_key("pose5", "A 5-D pose (position, pitch, yaw) in a named convention and angle unit",
                        json!({ "type": "object", "required": ["x", "y", "z", "pitch", "yaw", "convention", "unit"], "additionalProperties": false,
                                "properties": {
                                    "x": { "type": "number", "minimum": -MAX_COORDINATE, "maximum": MAX_COORDINATE },
                                    "y": { "type": "number", "minimum": -MAX_COORDINATE, "maximum": MAX_COORDINATE },
                                    "z": { "type": "number", "minimum": -MAX_COORDINATE, "maximum": MAX_COORDINATE },
                                    "pitch": { "type": "number" },
                                    "yaw": { "type": "number" },
                                    "convention": { "enum": ["minecraft", "mineflayer", "worldmem"] },
                                    "unit": { "enum": ["degrees", "radians"] } } })),
                ],
                "example": { "c2w": { "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "position": [0.5, -1.62, 2.0] } },
            }),
        ),
        (
            "IntrinsicsInput",
            json!({
                "type": "object",
                "description": "A pinhole camera: fx (with optional fy, cx, cy) or hfov_deg (with optional vfov_deg); the principal point \
                                defaults to the image centre, near/far to 0.1/30 world units.",
                "required": ["width", "height"],
                "additionalProperties": false,
                "properties": {
                    "fx": { "type": "number", "exclusiveMinimum": 0 }, "fy": { "type": "number", "exclusiveMinimum": 0 },
                    "cx": { "type": "number" }, "cy": { "type": "number" },
                    "hfov_deg": { "type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 180 },
                    "vfov_deg": { "type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 180 },
                    "width": { "type": "integer", "minimum": 1, "maximum": 8192 }, "height": { "type": "integer", "minimum": 1, "maximum": 8192 },
                    "near": { "type": "number", "exclusiveMinimum": 0 }, "far": { "type": "number", "exclusiveMinimum": 0 },
                },
                "example": { "hfov_deg": 70, "width": 64, "height": 64 },
            }),
        ),
        (
            "Intrinsics",
            json!({
                "type": "object",
                "description": "The session's resolved camera (pixels; near and far in world units).",
                "properties": {
                    "fx": { "type": "number" }, "fy": { "type": "number" }, "cx": { "type": "number" }, "cy": { "type": "number" },
                    "width": { "type": "integer" }, "height": { "type": "integer" }, "near": { "type": "number" }, "far": { "type": "number" },
                },
            }),
        ),
        (
            "Action",
            json!({
                "type": "object",
                "description": "One step's controls (LoopNav's action space): movement keys, jump, and camera turns in degrees \
                                (positive yaw turns right, positive pitch looks down). Missing keys are false or 0.",
                "additionalProperties": false,
                "properties": {
                    "forward": { "type": "boolean" }, "back": { "type": "boolean" }, "left": { "type": "boolean" },
                    "right": { "type": "boolean" }, "jump": { "type": "boolean" },
                    "yaw_deg": { "type": "number", "minimum": -MAX_TURN_DEG, "maximum": MAX_TURN_DEG },
                    "pitch_deg": { "type": "number", "minimum": -MAX_TURN_DEG, "maximum": MAX_TURN_DEG },
                },
                "example": { "forward": true, "yaw_deg": 6 },
            }),
        ),
        (
            "PolicySpec",
            json!({
                "type": "object",
                "description": "A context policy: a preset (`kind`) with optional overrides; the server's --policy when absent.",
                "required": ["kind"],
                "additionalProperties": false,
                "properties": {
                    "kind": { "enum": kinds },
                    "query": { "enum": ["current", "target"], "description": "score against the newest frame's view (the paper's Algorithm 1) or against the target pose" },
                    "keep_last": { "type": "boolean", "description": "pin the newest frame to the first full-rate slot" },
                    "estimator": { "type": "object", "description": "the overlap estimator (docs/api.md)" },
                    "weights": { "type": "object", "properties": { "overlap": { "type": "number" }, "recency": { "type": "number" } } },
                    "tiers": { "type": "array", "items": { "type": "object", "properties": { "slots": { "type": "integer" }, "rate": { "type": "integer" } } } },
                    "covisibility": { "oneOf": [{ "$ref": "#/components/schemas/CoVisibility" }, { "type": "null" }],
                                      "description": "re-rank the frustum candidates by co-visibility from the observed frames' depth (`{}`: the defaults)" },
                },
                "example": { "kind": "worldpack", "covisibility": {} },
            }),
        ),
        (
            "Policy",
            json!({
                "type": "object",
                "description": "A session's policy with every setting resolved.",
                "required": ["kind", "ranking", "packing", "estimator", "weights", "keep_last", "query"],
                "properties": {
                    "kind": { "enum": kinds }, "ranking": {}, "packing": { "type": "object" }, "estimator": {},
                    "weights": { "type": "object" }, "keep_last": { "type": "boolean" }, "query": { "enum": ["current", "target"] },
                    "covisibility": { "oneOf": [{ "$ref": "#/components/schemas/CoVisibility" }, { "type": "null" }] },
                },
            }),
        ),
        (
            "CoVisibility",
            json!({
                "type": "object",
                "description": "Occlusion-aware selection (memory::covisibility): the policy's frustum candidates ranked by the share of \
                                the target view's expected surface each saw unoccluded, from the depth of the session's observed frames. \
                                Each setting defaults when left out.",
                "additionalProperties": false,
                "properties": {
                    "candidates": { "type": "integer", "minimum": 1, "maximum": CoVisibility::MAX_CANDIDATES,
                                    "description": format!("frames kept from the frustum stage (default {})", d.candidates) },
                    "sources": { "type": "integer", "minimum": 1, "maximum": CoVisibility::MAX_SOURCES,
                                 "description": format!("frames with depth whose surfaces make the expected surface (default {})", d.sources) },
                    "cells": { "type": "integer", "minimum": 1, "maximum": CoVisibility::MAX_CELLS,
                               "description": format!("columns of the coarse depth grid (default {})", d.cells) },
                    "tolerance": { "type": "number", "minimum": 0, "maximum": CoVisibility::MAX_TOLERANCE,
                                   "description": format!("how much deeper than a frame's recorded surface a point may lie and still count as seen, relative (default {})", d.tolerance) },
                },
                "example": { "cells": 16 },
            }),
        ),
        ("Biome", json!({ "enum": ["plains", "forest", "desert", "snowy", "mountains", "badlands"] })),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The foreign schemas' examples parse with the owning crates' parsers,
    /// and their enums are those crates' names.
    #[test]
    fn foreign_schemas_match_the_types_they_describe() {
        let all: std::collections::HashMap<&str, Value> = foreign_schemas().into_iter().collect();
        let schema = |name: &str| all[name].clone();
        let pose: memory::input::PoseInput = serde_json::from_value(schema("Pose")["example"].clone()).unwrap();
        pose.resolve().unwrap();
        let k: memory::input::IntrinsicsInput = serde_json::from_value(schema("IntrinsicsInput")["example"].clone()).unwrap();
        k.resolve().unwrap();
        let _: motion::Action = serde_json::from_value(schema("Action")["example"].clone()).unwrap();
        let policy = crate::session::policy_of(&schema("PolicySpec")["example"]).unwrap();
        assert_eq!(policy.covisibility, Some(memory::CoVisibility::default()));
        let c: memory::CoVisibility = serde_json::from_value(schema("CoVisibility")["example"].clone()).unwrap();
        c.validated().unwrap();
        for biome in schema("Biome")["enum"].as_array().unwrap() {
            let _: world::Biome = serde_json::from_value(biome.clone()).unwrap();
        }
        for form in schema("Pose")["oneOf"].as_array().unwrap() {
            let key = form["required"][0].as_str().unwrap();
            assert!(["c2w", "opencv", "opengl", "pose5"].contains(&key), "{key}");
        }
        let pose5 = &schema("Pose")["oneOf"][3]["properties"]["pose5"]["properties"];
        for convention in pose5["convention"]["enum"].as_array().unwrap() {
            let _: memory::Pose5Convention = serde_json::from_value(convention.clone()).unwrap();
        }
    }
}
