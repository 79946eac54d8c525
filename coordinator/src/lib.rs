//! pathfarm coordinator, in three floors, each importing only from the floors below it:
//!
//! - [`farm`]: the pure state machine (jobs, frames, units, workers, leases, scheduling, the
//!   merge); no I/O, no async, an explicit clock.
//! - [`service`]: the running service around it: shared state, the SQLite store and
//!   checkpoints, scene storage, progressive output, background loops, webhooks, metrics.
//! - [`http`]: the REST API over the service: errors, auth, routes per resource, server-sent
//!   events, the dashboard, the OpenAPI document, the accept loop.
//!
//! [`server`] wires them together; [`client`], [`local`] and [`demo`] are users of the API.

pub mod client;
pub mod demo;
pub mod farm;
pub mod http;
pub mod local;
pub mod server;
pub mod service;

#[cfg(test)]
mod floors {
    //! The floor rule, checked on the source: no import runs back up a floor.

    use std::path::Path;

    /// Paths a file on each floor must not name: (floor folder, forbidden paths).
    const RULES: [(&str, &[&str]); 2] = [
        ("farm", &["crate::service", "crate::http", "crate::server", "tokio", "axum", "rusqlite"]),
        ("service", &["crate::http", "crate::server", "axum", "hyper"]),
    ];

    /// The forbidden paths that `source` names outside comments, with their line numbers.
    fn violations(source: &str, forbidden: &[&str]) -> Vec<(usize, String)> {
        source
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim_start().starts_with("//"))
            .flat_map(|(i, l)| {
                forbidden
                    .iter()
                    .filter(move |f| {
                        l.match_indices(**f).any(|(at, _)| {
                            // A whole path segment: `tokio::`, `crate::http::`, `crate::http;`...
                            let before = l[..at].chars().next_back();
                            let after = l[at + f.len()..].chars().next();
                            !before.is_some_and(|c| c.is_alphanumeric() || c == '_')
                                && !after.is_some_and(|c| c.is_alphanumeric() || c == '_')
                        })
                    })
                    .map(move |f| (i + 1, f.to_string()))
            })
            .collect()
    }

    fn rust_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
        for entry in std::fs::read_dir(dir).expect("read the floor's folder") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                rust_files(&path, out);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }

    #[test]
    fn no_import_runs_back_up_a_floor() {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut found = Vec::new();
        for (floor, forbidden) in RULES {
            let mut files = Vec::new();
            rust_files(&src.join(floor), &mut files);
            assert!(!files.is_empty(), "no sources under src/{floor}");
            for file in files {
                let text = std::fs::read_to_string(&file).expect("read source");
                for (line, path) in violations(&text, forbidden) {
                    found.push(format!("{}:{line} names {path}", file.display()));
                }
            }
        }
        assert!(found.is_empty(), "imports running back up a floor:\n{}", found.join("\n"));
    }

    #[test]
    fn the_floor_check_finds_an_upward_import() {
        let farm = RULES[0].1;
        assert_eq!(violations("use crate::service::AppState;", farm), vec![(1, "crate::service".to_string())]);
        assert_eq!(violations("fn f() {\n    tokio::spawn(g());\n}", farm), vec![(2, "tokio".to_string())]);
        assert_eq!(violations("let x = crate::http::router(s);", RULES[1].1).len(), 1);
        // Comments and longer names are not imports.
        assert!(violations("// crate::service is above us\nuse crate::services_of_mine::X;", farm).is_empty());
        assert!(violations("use my_tokio_helpers::X;", farm).is_empty());
    }
}
