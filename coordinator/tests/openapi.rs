//! The OpenAPI document covers the router, both ways:
//! - every `.route(routes::NAME, METHODS)` registered in the source (http/mod.rs, http/dashboard.rs) is in the
//!   document with each of its methods (a route added without docs fails here);
//! - every documented (path, method) is served by the real router (not the fallback);
//! - every schema reference resolves, and `/api/v1/openapi.json` serves the document.

use axum::body::Body;
use axum::http::{Method, Request, StatusCode};
use pathfarm_coordinator::server::{AppState, ServerConfig};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use tower::ServiceExt;

const API: &str = "/api/v1";

/// `(path, method)` pairs of the document.
fn documented() -> BTreeSet<(String, String)> {
    let doc = serde_json::to_value(pathfarm_coordinator::http::openapi::document()).expect("serialize");
    let mut out = BTreeSet::new();
    for (path, item) in doc["paths"].as_object().expect("paths") {
        for method in ["get", "post", "put", "delete", "patch", "head", "options"] {
            if item.get(method).is_some() {
                out.insert((path.clone(), method.to_string()));
            }
        }
    }
    out
}

/// `.route("PATH", get(..).post(..))` calls in a source file; `prefix` applies to routes that
/// come before the line containing `prefix_until` (the nested API routers in http/mod.rs).
fn routes_in_source(src: &str, prefix: &str, prefix_until: Option<&str>) -> BTreeSet<(String, String)> {
    let boundary = prefix_until.and_then(|m| src.find(m)).unwrap_or(usize::MAX);
    let mut out = BTreeSet::new();
    let mut rest = 0;
    while let Some(i) = src[rest..].find(".route(") {
        let start = rest + i;
        // The call's text, up to its matching parenthesis.
        let mut depth = 0;
        let mut end = start;
        for (k, c) in src[start..].char_indices() {
            match c {
                '(' => depth += 1,
                ')' => {
                    depth -= 1;
                    if depth == 0 {
                        end = start + k;
                        break;
                    }
                }
                _ => {}
            }
        }
        let call = &src[start + ".route(".len()..end];
        rest = end.max(start + 1);
        // The path is a `routes::NAME` constant (one definition of each URL path).
        let q0 = call.find("routes::").expect("route path: a routes:: constant") + "routes::".len();
        let q1 = q0 + call[q0..].find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).expect("end of name");
        let name = &call[q0..q1];
        let path = pathfarm_common::routes::ALL
            .iter()
            .find(|(n, _)| *n == name)
            .unwrap_or_else(|| panic!("routes::{name} is not in routes::ALL"))
            .1;
        // Nested under the API prefix, or prefixed in the call itself (`format!("{API}{}", ..)`).
        let prefixed = start < boundary || call[..q0].contains("{API}");
        let path = if prefixed { format!("{prefix}{path}") } else { path.to_string() };
        let methods = &call[q1..];
        let mut found = false;
        for m in ["get", "post", "put", "delete", "patch"] {
            // `get(`, `.get(`, but not `forget(` or `DefaultBodyLimit::max(`.
            let mut from = 0;
            while let Some(j) = methods[from..].find(&format!("{m}(")) {
                let at = from + j;
                let before = methods[..at].chars().last();
                if before.is_none_or(|c| !(c.is_alphanumeric() || c == '_' || c == ':')) {
                    out.insert((path.clone(), m.to_string()));
                    found = true;
                }
                from = at + 1;
            }
        }
        assert!(found, "no method found in route {path}: {call}");
    }
    out
}

fn registered() -> BTreeSet<(String, String)> {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/src/");
    let api = std::fs::read_to_string(format!("{dir}http/mod.rs")).expect("http/mod.rs");
    let dash = std::fs::read_to_string(format!("{dir}http/dashboard.rs")).expect("http/dashboard.rs");
    let mut all = routes_in_source(&api, API, Some(".nest(API"));
    // Served at the root; only the calls that write `{API}` themselves are under the prefix.
    all.extend(routes_in_source(&dash, API, Some("Router::new()")));
    all
}

#[test]
fn every_registered_route_is_documented() {
    let registered = registered();
    assert!(registered.len() >= 25, "the route parser found too few routes: {registered:?}");
    assert!(registered.contains(&("/api/v1/jobs/{id}/cancel".into(), "post".into())), "{registered:?}");
    assert!(registered.contains(&("/healthz".into(), "get".into())), "{registered:?}");
    let documented = documented();
    let missing: Vec<_> = registered.difference(&documented).collect();
    assert!(
        missing.is_empty(),
        "routes without OpenAPI docs (add #[utoipa::path] and list them in openapi.rs): {missing:?}"
    );
    let extra: Vec<_> = documented.difference(&registered).collect();
    assert!(extra.is_empty(), "documented routes that the source does not register: {extra:?}");
}

fn state() -> (tempfile::TempDir, Arc<AppState>) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), tmp.path().to_path_buf());
    let state = Arc::new(AppState::new(cfg).expect("state"));
    (tmp, state)
}

#[tokio::test]
async fn every_documented_route_is_served() {
    let (_tmp, state) = state();
    let app = pathfarm_coordinator::http::router(state);
    for (path, method) in documented() {
        let uri = path.replace("{id}", "1");
        let method = Method::from_bytes(method.to_uppercase().as_bytes()).expect("method");
        let req = Request::builder().method(method.clone()).uri(&uri).body(Body::empty()).expect("request");
        let resp = app.clone().oneshot(req).await.expect("response");
        let status = resp.status();
        assert_ne!(status, StatusCode::METHOD_NOT_ALLOWED, "{method} {uri} is documented but not routed");
        if status == StatusCode::NOT_FOUND {
            let body = axum::body::to_bytes(resp.into_body(), 1 << 20).await.expect("body");
            let text = String::from_utf8_lossy(&body);
            assert!(!text.contains("no such route"), "{method} {uri} is documented but not routed: {text}");
        }
    }
}

fn refs(v: &serde_json::Value, out: &mut BTreeSet<String>) {
    match v {
        serde_json::Value::Object(o) => {
            for (k, v) in o {
                if k == "$ref"
                    && let Some(s) = v.as_str()
                {
                    out.insert(s.to_string());
                }
                refs(v, out);
            }
        }
        serde_json::Value::Array(a) => a.iter().for_each(|v| refs(v, out)),
        _ => {}
    }
}

#[tokio::test]
async fn document_is_served_and_self_consistent() {
    let (_tmp, state) = state();
    let app = pathfarm_coordinator::http::router(state);
    let req = Request::builder().uri("/api/v1/openapi.json").body(Body::empty()).expect("request");
    let resp = app.oneshot(req).await.expect("response");
    assert_eq!(resp.status(), StatusCode::OK);
    let body = axum::body::to_bytes(resp.into_body(), 16 << 20).await.expect("body");
    let doc: serde_json::Value = serde_json::from_slice(&body).expect("JSON");
    assert!(doc["openapi"].as_str().is_some_and(|v| v.starts_with("3.")), "{}", doc["openapi"]);
    let schemas: BTreeMap<String, serde_json::Value> =
        serde_json::from_value(doc["components"]["schemas"].clone()).expect("schemas");
    for name in ["JobInfo", "WorkerInfo", "RenderSettings", "IntegratorSettings", "JobRequestBody", "ErrorBody"] {
        assert!(schemas.contains_key(name), "schema {name} missing");
    }
    let mut all = BTreeSet::new();
    refs(&doc, &mut all);
    for r in all {
        let name = r.strip_prefix("#/components/schemas/").unwrap_or_else(|| panic!("unexpected $ref {r}"));
        assert!(schemas.contains_key(name), "dangling $ref {r}");
    }
    let security = doc["components"]["securitySchemes"].as_object().expect("security schemes");
    assert!(security.contains_key("client_token") && security.contains_key("worker_token"));
}

/// Binary bodies are typed as binary (`format: binary`, `contentMediaType`), never as arrays of
/// integers, so generated clients send and receive bytes: scene uploads and downloads, result
/// frames, the EXR and the PNG.
#[test]
fn binary_bodies_are_typed_binary() {
    let doc = serde_json::to_value(pathfarm_coordinator::http::openapi::document()).expect("serialize");
    let expect_binary = |schema: &serde_json::Value, media: &str, at: &str| {
        assert_eq!(schema["type"], "string", "{at}: {schema}");
        assert_eq!(schema["format"], "binary", "{at}: {schema}");
        assert_eq!(schema["contentMediaType"], media, "{at}: {schema}");
    };
    let upload = &doc["paths"]["/api/v1/scenes"]["post"]["requestBody"]["content"]["application/octet-stream"];
    expect_binary(&upload["schema"], "application/octet-stream", "POST /scenes body");
    let result =
        &doc["paths"]["/api/v1/leases/{id}/result"]["put"]["requestBody"]["content"]["application/octet-stream"];
    expect_binary(&result["schema"], "application/octet-stream", "PUT /leases/{id}/result body");
    let download =
        &doc["paths"]["/api/v1/scenes/{id}"]["get"]["responses"]["200"]["content"]["application/octet-stream"];
    expect_binary(&download["schema"], "application/octet-stream", "GET /scenes/{id}");
    let exr = &doc["paths"]["/api/v1/jobs/{id}/image.exr"]["get"]["responses"]["200"]["content"]["image/x-exr"];
    expect_binary(&exr["schema"], "image/x-exr", "GET image.exr");
    let png = &doc["paths"]["/api/v1/jobs/{id}/preview.png"]["get"]["responses"]["200"]["content"]["image/png"];
    expect_binary(&png["schema"], "image/png", "GET preview.png");
    // Every non-text body in the document is binary.
    let mut checked = 0;
    for (path, item) in doc["paths"].as_object().expect("paths") {
        for (method, op) in item.as_object().expect("path item") {
            let mut contents: Vec<&serde_json::Value> = vec![&op["requestBody"]["content"]];
            if let Some(responses) = op["responses"].as_object() {
                contents.extend(responses.values().map(|r| &r["content"]));
            }
            for content in contents.into_iter().filter_map(|c| c.as_object()) {
                for (media, c) in content {
                    if media == "application/octet-stream" || media.starts_with("image/") {
                        expect_binary(&c["schema"], media, &format!("{method} {path}"));
                        checked += 1;
                    }
                }
            }
        }
    }
    assert!(checked >= 5, "only {checked} binary bodies found");
}

/// No `"items": false` (utoipa's tuples) anywhere in the served document: generators refuse it. Tuples keep their
/// length and per-position types.
#[test]
fn tuples_are_arrays_of_fixed_length() {
    let doc = serde_json::to_value(pathfarm_coordinator::http::openapi::document_json()).expect("serialize");
    let text = doc.to_string();
    assert!(!text.contains(r#""items":false"#), "a tuple is left with items: false");
    let current = &doc["components"]["schemas"]["WorkerInfo"]["properties"]["current"];
    assert_eq!(current["prefixItems"].as_array().map(Vec::len), Some(2), "{current}");
    assert_eq!((current["minItems"].as_u64(), current["maxItems"].as_u64()), (Some(2), Some(2)), "{current}");
}

#[test]
fn the_job_body_spells_every_render_setting() {
    // JobRequestBody repeats RenderSettings' fields by hand (see openapi.rs): a new setting
    // must be documented there too.
    let doc = serde_json::to_value(pathfarm_coordinator::http::openapi::document()).expect("serialize");
    let schemas = &doc["components"]["schemas"];
    let names = |schema: &serde_json::Value| -> BTreeSet<String> {
        schema["properties"].as_object().map(|p| p.keys().cloned().collect()).unwrap_or_default()
    };
    let settings = names(&schemas["RenderSettings"]);
    let body = names(&schemas["JobRequestBody"]);
    assert!(settings.contains("environment"), "{settings:?}");
    let missing: Vec<_> = settings.difference(&body).collect();
    assert!(missing.is_empty(), "JobRequestBody lacks {missing:?}");
}
