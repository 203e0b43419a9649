//! The OpenAPI document, derived from the request and response types
//! (`utoipa`) and the handlers' annotations in `routes`, with the schemas of
//! foreign types from `schemas`.

use serde_json::{Value, json};
use utoipa::OpenApi;

use crate::{routes, schemas};

#[derive(OpenApi)]
#[openapi(
    info(
        title = "WorldPack",
        description = "Geometry-first memory and a packed-context world model. Every error is a JSON body naming the field: \
                       {\"error\": {\"field\": ..., \"message\": ...}}. See docs/api.md."
    ),
    paths(
        routes::health,
        routes::ready,
        routes::list,
        routes::metrics,
        routes::create,
        routes::describe,
        routes::delete,
        routes::fork,
        routes::step,
        routes::imagine,
        routes::observe,
        routes::select,
        routes::frame,
        routes::frame_image,
        routes::frame_depth,
        routes::frame_truth
    )
)]
struct ApiDoc;

/// The document `/openapi.json` serves and `/docs` shows.
pub fn document() -> Value {
    let mut doc = serde_json::to_value(ApiDoc::openapi()).expect("an OpenAPI document serialises");
    let components = doc["components"]["schemas"].as_object_mut().expect("the derived document has component schemas");
    for (name, schema) in schemas::foreign_schemas() {
        components.insert(name.to_string(), schema);
    }
    // Links: what a created session and a stepped frame lead to (clients and
    // stateful testers follow them instead of guessing ids).
    let session = json!({ "id": "$response.body#/session" });
    let frame = json!({ "id": "$response.body#/session", "index": "$response.body#/index" });
    let paths = &mut doc["paths"];
    paths["/v1/sessions"]["post"]["responses"]["201"]["links"] = json!({
        "Describe": { "operationId": "describe", "parameters": session },
        "Step": { "operationId": "step", "parameters": session },
        "Observe": { "operationId": "observe", "parameters": session },
        "Select": { "operationId": "select", "parameters": session },
        "Delete": { "operationId": "delete", "parameters": session },
        "Fork": { "operationId": "fork", "parameters": session },
        "Imagine": { "operationId": "imagine", "parameters": session },
    });
    // A fork is a session: the same operations apply to it.
    paths["/v1/sessions/{id}/fork"]["post"]["responses"]["201"]["links"] = json!({
        "Describe": { "operationId": "describe", "parameters": session },
        "Step": { "operationId": "step", "parameters": session },
        "Imagine": { "operationId": "imagine", "parameters": session },
        "Delete": { "operationId": "delete", "parameters": session },
    });
    for (path, method, status) in [("/v1/sessions/{id}/step", "post", "200"), ("/v1/sessions/{id}/observe", "post", "200")] {
        paths[path][method]["responses"][status]["links"] = json!({
            "Frame": { "operationId": "frame", "parameters": frame },
            "Image": { "operationId": "frame_image", "parameters": frame },
            "Depth": { "operationId": "frame_depth", "parameters": frame },
            "Truth": { "operationId": "frame_truth", "parameters": frame },
        });
    }
    // Tokens (docs/api.md): a server started with them needs a bearer token on
    // every /v1 route and may refuse a tenant over its rate; one without them
    // takes requests without (the empty requirement).
    doc["components"]["securitySchemes"] = json!({ "bearer": { "type": "http", "scheme": "bearer" } });
    doc["security"] = json!([{ "bearer": [] }, {}]);
    let error = json!({ "application/json": { "schema": { "$ref": "#/components/schemas/ErrorBody" } } });
    for (path, item) in doc["paths"].as_object_mut().expect("the document has paths") {
        if !path.starts_with("/v1/") {
            continue;
        }
        for operation in item.as_object_mut().expect("a path item is an object").values_mut() {
            let responses = &mut operation["responses"];
            responses["401"] = json!({ "description": "tokens are configured and this request has none, or an unknown one (field `authorization`; `WWW-Authenticate: Bearer`)", "content": error });
            if responses.get("429").is_none() {
                responses["429"] = json!({ "description": "the tenant is over its request rate (or its session limit); retry after `Retry-After` seconds", "content": error });
            }
        }
    }
    let schemas = &mut doc["components"]["schemas"];
    // What the derive cannot state: a session starts from a synthetic world or from frames with intrinsics, not both.
    schemas["CreateRequest"]["oneOf"] = json!([
        { "required": ["synthetic"], "not": { "anyOf": [{ "required": ["frames"] }, { "required": ["intrinsics"] }] } },
        { "required": ["frames", "intrinsics"], "not": { "required": ["synthetic"] } },
    ]);
    doc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_path_and_reference_resolves() {
        let doc = document();
        assert_eq!(doc["openapi"], "3.1.0");
        assert_eq!(doc["paths"].as_object().unwrap().len(), 14);
        assert_eq!(doc["components"]["securitySchemes"]["bearer"]["scheme"], "bearer");
        assert!(doc["paths"]["/v1/sessions/{id}/step"]["post"]["responses"]["401"].is_object());
        let text = doc.to_string();
        for (at, _) in text.match_indices("#/components/schemas/") {
            let name: String = text[at + 21..].chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
            assert!(doc["components"]["schemas"][&name].is_object(), "{name} is referenced but not defined");
        }
    }
}
