//! A blocking client of the REST API, used by the `pathfarm` CLI, the demo and the tests.

use anyhow::{Context, bail};
use pathfarm_common::protocol::{
    API, ErrorBody, FrameInfo, FrameState, JobCreated, JobId, JobInfo, JobRequest, JobState, MAX_PAGE_LIMIT,
    SceneCreated,
};
use pathfarm_common::routes;
use reqwest::blocking::{Client as Http, RequestBuilder, Response};
use std::time::Duration;

pub struct Client {
    base: String,
    token: Option<String>,
    http: Http,
}

fn check(resp: Response) -> anyhow::Result<Response> {
    if resp.status().is_success() {
        return Ok(resp);
    }
    let status = resp.status();
    let text = resp.text().unwrap_or_default();
    match serde_json::from_str::<ErrorBody>(&text) {
        Ok(e) => bail!("{status}: {} ({})", e.error.message, e.error.code),
        Err(_) => bail!("{status}: {text}"),
    }
}

impl Client {
    pub fn new(base: &str, token: Option<String>) -> anyhow::Result<Self> {
        Self::with_ca_cert(base, token, None)
    }

    /// A client that also trusts the PEM certificate(s) in `ca_cert` (else `PATHFARM_CA_CERT`).
    pub fn with_ca_cert(base: &str, token: Option<String>, ca_cert: Option<&std::path::Path>) -> anyhow::Result<Self> {
        let http = pathfarm_worker::daemon::with_ca_cert(Http::builder().timeout(Duration::from_secs(300)), ca_cert)?
            .build()?;
        Ok(Self { base: base.trim_end_matches('/').to_string(), token, http })
    }

    fn req(&self, rb: RequestBuilder) -> anyhow::Result<Response> {
        let rb = match &self.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        };
        check(rb.send().with_context(|| format!("cannot reach the coordinator at {}", self.base))?)
    }

    fn url(&self, path: &str) -> String {
        format!("{}{API}{path}", self.base)
    }

    pub fn upload_scene(&self, bytes: Vec<u8>) -> anyhow::Result<SceneCreated> {
        Ok(self.req(self.http.post(self.url(routes::SCENES)).body(bytes))?.json()?)
    }

    pub fn submit(&self, job: &JobRequest) -> anyhow::Result<JobId> {
        Ok(self.submit_job(job)?.id)
    }

    /// `POST /jobs`: the new job's id and the coordinator's warnings about it.
    pub fn submit_job(&self, job: &JobRequest) -> anyhow::Result<JobCreated> {
        Ok(self.req(self.http.post(self.url(routes::JOBS)).json(&job.to_json()))?.json()?)
    }

    pub fn job(&self, id: JobId) -> anyhow::Result<JobInfo> {
        Ok(self.req(self.http.get(self.url(&routes::fill(routes::JOB, &[&id]))))?.json()?)
    }

    /// Every job: the list is paged, so this asks page after page.
    pub fn jobs(&self) -> anyhow::Result<Vec<JobInfo>> {
        let mut all: Vec<JobInfo> = Vec::new();
        loop {
            let mut path = format!("{}?limit={MAX_PAGE_LIMIT}", routes::JOBS);
            if let Some(last) = all.last() {
                path.push_str(&format!("&after={}", last.id));
            }
            let page: Vec<JobInfo> = self.req(self.http.get(self.url(&path)))?.json()?;
            let done = page.len() < MAX_PAGE_LIMIT;
            all.extend(page);
            if done {
                return Ok(all);
            }
        }
    }

    pub fn cancel(&self, id: JobId) -> anyhow::Result<JobInfo> {
        Ok(self.req(self.http.post(self.url(&routes::fill(routes::JOB_CANCEL, &[&id]))))?.json()?)
    }

    pub fn image_exr(&self, id: JobId) -> anyhow::Result<Vec<u8>> {
        Ok(self.req(self.http.get(self.url(&routes::fill(routes::JOB_EXR, &[&id]))))?.bytes()?.to_vec())
    }

    pub fn preview_png(&self, id: JobId) -> anyhow::Result<Vec<u8>> {
        Ok(self.req(self.http.get(self.url(&routes::fill(routes::JOB_PNG, &[&id]))))?.bytes()?.to_vec())
    }

    /// Every frame of a job with its state (the list is paged).
    pub fn frames(&self, id: JobId) -> anyhow::Result<Vec<FrameInfo>> {
        let mut all: Vec<FrameInfo> = Vec::new();
        loop {
            let mut path = format!("{}?limit={MAX_PAGE_LIMIT}", routes::fill(routes::JOB_FRAMES, &[&id]));
            if let Some(last) = all.last() {
                path.push_str(&format!("&after={}", last.index));
            }
            let page: Vec<FrameInfo> = self.req(self.http.get(self.url(&path)))?.json()?;
            let done = page.len() < MAX_PAGE_LIMIT;
            all.extend(page);
            if done {
                return Ok(all);
            }
        }
    }

    pub fn frame_exr(&self, id: JobId, frame: i32) -> anyhow::Result<Vec<u8>> {
        Ok(self.req(self.http.get(self.url(&routes::fill(routes::FRAME_EXR, &[&id, &frame]))))?.bytes()?.to_vec())
    }

    pub fn frame_png(&self, id: JobId, frame: i32) -> anyhow::Result<Vec<u8>> {
        Ok(self.req(self.http.get(self.url(&routes::fill(routes::FRAME_PNG, &[&id, &frame]))))?.bytes()?.to_vec())
    }

    /// Writes a job's images: a single-frame job's EXR to `out`; every started frame of a
    /// sequence to `frame_path(out, frame)` (`shot.####.exr` -> `shot.0001.exr`, ...). Frames
    /// not started are skipped. Returns the files written.
    pub fn fetch_images(&self, id: JobId, out: &str) -> anyhow::Result<Vec<std::path::PathBuf>> {
        let write = |path: &std::path::Path, bytes: Vec<u8>| -> anyhow::Result<()> {
            if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            }
            std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
        };
        let info = self.job(id)?;
        if !info.frames.sequence {
            let path = std::path::PathBuf::from(out);
            write(&path, self.image_exr(id)?)?;
            return Ok(vec![path]);
        }
        let mut written = Vec::new();
        for f in self.frames(id)?.into_iter().filter(|f| f.state != FrameState::Pending) {
            let path = std::path::PathBuf::from(pathfarm_common::frames::frame_path(out, f.frame));
            write(&path, self.frame_exr(id, f.frame)?)?;
            written.push(path);
        }
        Ok(written)
    }

    /// Polls until the job ends, showing a progress bar on a terminal.
    pub fn wait(&self, id: JobId, show_progress: bool) -> anyhow::Result<JobInfo> {
        let bar = indicatif::ProgressBar::new(1000);
        if show_progress {
            bar.set_style(
                indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:40} {percent}% {msg}")
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
        } else {
            bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
        }
        loop {
            let info = self.job(id)?;
            bar.set_position((info.progress * 1000.0) as u64);
            let frames = if info.frames.sequence {
                format!("frames {}/{}  ", info.frames.done, info.frames.total)
            } else {
                String::new()
            };
            bar.set_message(format!(
                "{} {frames}spp {}/{}  {:.2} Msamples/s",
                info.state.as_str(),
                info.spp_done,
                info.settings.spp,
                info.samples_per_sec / 1e6
            ));
            if info.state.is_finished() {
                bar.finish();
                if info.state == JobState::Failed {
                    bail!("job {id} failed: {}", info.error.unwrap_or_default());
                }
                return Ok(info);
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}
