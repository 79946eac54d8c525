//! Helpers shared by the end-to-end tests.

/// Real coordinator and worker processes on 127.0.0.1, an HTTP client, and checks of the JSON
/// error body. The binaries are found next to the test executable
/// (`target/release/deps/xxx` -> `target/release/`); build them first with
/// `cargo build --release -p pathfarm-coordinator -p pathfarm-worker`.
pub mod procs {
    use anyhow::{Context, bail};
    use pathfarm_common::protocol::{API, JobInfo, JobState, Registered, WORKER_SECRET_HEADER};
    use reqwest::StatusCode;
    use reqwest::blocking::{Client, RequestBuilder, Response};
    use std::path::{Path, PathBuf};
    use std::process::{Child, Command, Stdio};
    use std::time::{Duration, Instant};

    /// `target/<profile>/`, where cargo puts the binaries.
    pub fn bin_dir() -> PathBuf {
        let exe = std::env::current_exe().expect("current_exe");
        let mut dir = exe.parent().expect("exe dir").to_path_buf();
        if dir.ends_with("deps") {
            dir.pop();
        }
        dir
    }

    /// Path of a workspace binary, with a clear panic if it was not built.
    pub fn bin(name: &str) -> PathBuf {
        let p = bin_dir().join(name);
        assert!(
            p.exists(),
            "{} is missing: run `cargo build --release -p pathfarm-coordinator -p pathfarm-worker` first",
            p.display()
        );
        p
    }

    /// A blocking HTTP client with a generous timeout.
    pub fn http() -> Client {
        Client::builder().timeout(Duration::from_secs(60)).build().expect("http client")
    }

    /// A child process killed when dropped.
    pub struct Proc {
        pub child: Child,
    }

    impl Proc {
        /// SIGKILL and reap.
        pub fn kill(&mut self) {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }

        /// Sends SIGTERM and waits up to `timeout` for the process to exit.
        pub fn terminate(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
            let _ = Command::new("kill").arg("-TERM").arg(self.child.id().to_string()).status();
            let t0 = Instant::now();
            while t0.elapsed() < timeout {
                if let Ok(Some(s)) = self.child.try_wait() {
                    return Some(s);
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            None
        }
    }

    impl Drop for Proc {
        fn drop(&mut self) {
            self.kill();
        }
    }

    /// A coordinator process with its own data directory.
    pub struct Coordinator {
        pub proc: Proc,
        pub dir: tempfile::TempDir,
        /// `http://127.0.0.1:PORT`
        pub url: String,
        pub client_token: Option<String>,
        pub worker_token: Option<String>,
        pub http: Client,
    }

    impl Coordinator {
        /// Starts `pathfarm-coordinator --listen 127.0.0.1:0 --data-dir TMP EXTRA...` (with
        /// `--no-auth` unless `extra` gives tokens) and waits until it answers `/healthz`. Tokens
        /// given in `extra` are picked up for the helpers.
        pub fn start(extra: &[&str]) -> anyhow::Result<Self> {
            let dir = tempfile::tempdir()?;
            let log = std::fs::File::create(dir.path().join("coordinator.log"))?;
            let with_tokens = extra.iter().any(|a| a.ends_with("-token"));
            let child = Command::new(bin("pathfarm-coordinator"))
                .arg("--listen")
                .arg("127.0.0.1:0")
                .args(if with_tokens { &[][..] } else { &["--no-auth"][..] })
                .arg("--data-dir")
                .arg(dir.path())
                .args(extra)
                .env("RUST_LOG", "warn")
                .env_remove("PATHFARM_CLIENT_TOKEN")
                .env_remove("PATHFARM_WORKER_TOKEN")
                .stdout(Stdio::null())
                .stderr(log)
                .spawn()
                .context("spawning the coordinator")?;
            let mut proc = Proc { child };
            let flag = |name: &str| {
                extra.iter().position(|a| *a == name).and_then(|i| extra.get(i + 1)).map(|s| s.to_string())
            };
            let addr_file = dir.path().join("coordinator.addr");
            let t0 = Instant::now();
            let addr = loop {
                if let Ok(a) = std::fs::read_to_string(&addr_file)
                    && !a.trim().is_empty()
                {
                    break a.trim().to_string();
                }
                if let Some(status) = proc.child.try_wait()? {
                    let log = std::fs::read_to_string(dir.path().join("coordinator.log")).unwrap_or_default();
                    bail!("the coordinator exited with {status}: {log}");
                }
                if t0.elapsed() > Duration::from_secs(20) {
                    bail!("the coordinator did not write {} in 20 s", addr_file.display());
                }
                std::thread::sleep(Duration::from_millis(20));
            };
            let c = Self {
                proc,
                url: format!("http://{addr}"),
                client_token: flag("--client-token"),
                worker_token: flag("--worker-token"),
                http: http(),
                dir,
            };
            c.wait_healthy()?;
            Ok(c)
        }

        /// Full URL of an API path (`/jobs` -> `http://.../api/v1/jobs`).
        pub fn api(&self, path: &str) -> String {
            format!("{}{API}{path}", self.url)
        }

        /// A request with the client token (if any).
        pub fn client(&self, rb: RequestBuilder) -> RequestBuilder {
            match &self.client_token {
                Some(t) => rb.bearer_auth(t),
                None => rb,
            }
        }

        /// A request with the worker token (if any).
        pub fn worker(&self, rb: RequestBuilder) -> RequestBuilder {
            match &self.worker_token {
                Some(t) => rb.bearer_auth(t),
                None => rb,
            }
        }

        /// A request of a registered worker: the worker token (if any) and the worker's own
        /// secret.
        pub fn as_worker(&self, rb: RequestBuilder, reg: &Registered) -> RequestBuilder {
            self.worker(rb).header(WORKER_SECRET_HEADER, &reg.worker_secret)
        }

        /// Registers a worker by hand (`POST /workers/register`), which must succeed.
        pub fn register(&self, name: &str) -> Registered {
            let r = self
                .worker(self.http.post(self.api("/workers/register")))
                .json(&serde_json::json!({"name": name, "threads": 1}))
                .send()
                .expect("POST /workers/register");
            assert_eq!(r.status(), StatusCode::OK);
            r.json().expect("registered")
        }

        /// Waits until `/healthz` answers `ok` and the process is alive.
        pub fn wait_healthy(&self) -> anyhow::Result<()> {
            let t0 = Instant::now();
            loop {
                if let Ok(r) = self.http.get(format!("{}/healthz", self.url)).send()
                    && r.status() == StatusCode::OK
                {
                    return Ok(());
                }
                if t0.elapsed() > Duration::from_secs(20) {
                    bail!("the coordinator does not answer /healthz: {}", self.log());
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        }

        /// Asserts the server still serves: `/healthz` is `ok` and `GET /jobs` is 200.
        pub fn assert_serving(&mut self) {
            assert!(self.proc.child.try_wait().expect("try_wait").is_none(), "the coordinator died: {}", self.log());
            let r = self.http.get(format!("{}/healthz", self.url)).send().expect("healthz");
            assert_eq!(r.status(), StatusCode::OK);
            assert_eq!(r.text().expect("body"), "ok");
            let r = self.client(self.http.get(self.api("/jobs"))).send().expect("jobs");
            assert_eq!(r.status(), StatusCode::OK);
        }

        /// The coordinator's stderr so far.
        pub fn log(&self) -> String {
            std::fs::read_to_string(self.dir.path().join("coordinator.log")).unwrap_or_default()
        }

        /// Uploads a scene bundle and returns the raw response.
        pub fn upload(&self, bytes: Vec<u8>) -> Response {
            self.client(self.http.post(self.api("/scenes")))
                .header("content-type", "application/octet-stream")
                .body(bytes)
                .send()
                .expect("POST /scenes")
        }

        /// Uploads a scene that must be accepted; returns its id.
        pub fn upload_ok(&self, bytes: Vec<u8>) -> String {
            let r = self.upload(bytes);
            let status = r.status();
            let v: serde_json::Value = r.json().expect("scene answer");
            assert_eq!(status, StatusCode::CREATED, "{v}");
            v["scene_id"].as_str().expect("scene_id").to_string()
        }

        /// Submits a job body (JSON) and returns the raw response.
        pub fn submit(&self, body: &serde_json::Value) -> Response {
            self.client(self.http.post(self.api("/jobs"))).json(body).send().expect("POST /jobs")
        }

        /// Submits a job that must be accepted; returns its id.
        pub fn submit_ok(&self, body: &serde_json::Value) -> u64 {
            let r = self.submit(body);
            let status = r.status();
            let v: serde_json::Value = r.json().expect("job answer");
            assert_eq!(status, StatusCode::CREATED, "{v}");
            v["id"].as_u64().expect("id")
        }

        pub fn job(&self, id: u64) -> JobInfo {
            self.client(self.http.get(self.api(&format!("/jobs/{id}"))))
                .send()
                .expect("GET job")
                .json()
                .expect("job info")
        }

        /// Waits until the job is finished (or `timeout`) and returns its info.
        pub fn wait_job(&self, id: u64, timeout: Duration) -> JobInfo {
            let t0 = Instant::now();
            loop {
                let info = self.job(id);
                if info.state.is_finished() {
                    return info;
                }
                assert!(t0.elapsed() < timeout, "job {id} not finished after {timeout:?}: {info:?}\n{}", self.log());
                std::thread::sleep(Duration::from_millis(50));
            }
        }

        /// Waits for completion and saves `/jobs/{id}/image.exr` to `out`.
        pub fn wait_completed_exr(&self, id: u64, timeout: Duration, out: &Path) {
            let info = self.wait_job(id, timeout);
            assert_eq!(info.state, JobState::Completed, "{info:?}");
            let r = self.client(self.http.get(self.api(&format!("/jobs/{id}/image.exr")))).send().expect("exr");
            assert_eq!(r.status(), StatusCode::OK);
            std::fs::write(out, r.bytes().expect("exr bytes")).expect("write exr");
        }

        /// Starts a `pathfarm-worker run --threads 1` process against this coordinator.
        pub fn start_worker(&self) -> anyhow::Result<Proc> {
            let cache = self.dir.path().join(format!("worker-cache-{}", Instant::now().elapsed().as_nanos()));
            let mut cmd = Command::new(bin("pathfarm-worker"));
            cmd.arg("run")
                .arg("--coordinator")
                .arg(&self.url)
                .arg("--threads")
                .arg("1")
                .arg("--cache-dir")
                .arg(cache)
                .env("RUST_LOG", "warn")
                .env_remove("PATHFARM_WORKER_TOKEN")
                .stdout(Stdio::null())
                .stderr(Stdio::null());
            if let Some(t) = &self.worker_token {
                cmd.arg("--token").arg(t);
            }
            Ok(Proc { child: cmd.spawn().context("spawning a worker")? })
        }
    }

    /// Checks an error answer: the status, the JSON body `{"error": {"code", "message"}}`, and that
    /// the message contains every one of `needles` (case-insensitive). Returns the message.
    pub fn expect_error(resp: Response, status: StatusCode, needles: &[&str]) -> String {
        let got = resp.status();
        let text = resp.text().expect("error body");
        assert_eq!(got, status, "body: {text}");
        let v: serde_json::Value =
            serde_json::from_str(&text).unwrap_or_else(|e| panic!("error body is not JSON ({e}): {text}"));
        let code = v["error"]["code"].as_str().unwrap_or_else(|| panic!("no error.code: {text}"));
        assert!(!code.is_empty(), "{text}");
        let message = v["error"]["message"].as_str().unwrap_or_else(|| panic!("no error.message: {text}"));
        let lower = message.to_lowercase();
        for n in needles {
            assert!(lower.contains(&n.to_lowercase()), "message {message:?} does not name {n:?}");
        }
        message.to_string()
    }

    /// The `error.code` of an error answer (status checked).
    pub fn error_code(resp: Response, status: StatusCode) -> String {
        let got = resp.status();
        let text = resp.text().expect("error body");
        assert_eq!(got, status, "body: {text}");
        let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("not JSON ({e}): {text}"));
        v["error"]["code"].as_str().unwrap_or_default().to_string()
    }

    /// Runs `pathfarm-worker render SCENE --out OUT ARGS...` (one thread, quiet).
    pub fn render_local(scene: &Path, out: &Path, args: &[&str]) -> anyhow::Result<()> {
        let o = Command::new(bin("pathfarm-worker"))
            .arg("render")
            .arg(scene)
            .arg("--out")
            .arg(out)
            .arg("--quiet")
            .arg("--threads")
            .arg("1")
            .args(args)
            .env("RUST_LOG", "warn")
            .output()?;
        if !o.status.success() {
            bail!("pathfarm-worker render failed: {}", String::from_utf8_lossy(&o.stderr));
        }
        Ok(())
    }

    /// Asserts two EXR files hold the same channels with bit-identical values.
    pub fn assert_exr_identical(a: &Path, b: &Path) {
        let a = pathfarm_common::film::read_exr(a).expect("read exr a");
        let b = pathfarm_common::film::read_exr(b).expect("read exr b");
        assert_eq!((a.width, a.height), (b.width, b.height));
        let names = |e: &pathfarm_common::film::ExrChannels| {
            let mut n: Vec<String> = e.channels.iter().map(|(n, _)| n.clone()).collect();
            n.sort();
            n
        };
        assert_eq!(names(&a), names(&b));
        assert!(
            a.channels.iter().any(|(_, v)| v.iter().any(|x| *x != 0.0 && x.is_finite())),
            "the image is blank: comparing it proves nothing"
        );
        for (name, va) in &a.channels {
            let vb = b.get(name).expect("channel");
            let same = va.len() == vb.len() && va.iter().zip(vb).all(|(x, y)| x.to_bits() == y.to_bits());
            assert!(same, "channel {name} differs");
        }
    }
}
