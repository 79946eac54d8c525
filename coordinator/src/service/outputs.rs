//! Progressive output: the EXR/PNG writer, the frame writer thread, the output loop, and the
//! banded resolve of a film.

use super::*;

/// Writes `image.exr` and `preview.png` of a job atomically.
/// The PNG is exposed as the job asks (`exposure`, `auto_exposure`); returns the EV it used.
/// The previews come first; the EXR is then made from the layers given up and streamed to its
/// file, so a 4K frame is not held twice (layers and channels) or as a whole encoded file.
pub fn write_outputs(
    dir: &Path,
    mut layers: ImageLayers,
    exposure: pathfarm_common::film::PreviewExposure,
) -> anyhow::Result<f32> {
    std::fs::create_dir_all(dir)?;
    let ev = layers.preview_ev(exposure);
    write_atomic(&dir.join("preview.png"), &layers.encode_png(ev)?)?;
    if let Some(denoised) = layers.denoised.take() {
        // The preview shows the denoised layer; the noisy one beside it (`?layer=noisy`).
        let noisy = layers.encode_png(layers.preview_ev(exposure));
        layers.denoised = Some(denoised);
        write_atomic(&dir.join(NOISY_PREVIEW), &noisy?)?;
    }
    layers.into_exr_file(&dir.join("image.exr"))?;
    Ok(ev)
}

/// Beside a single-frame job's `image.exr` once it holds the job's final image: the job's
/// `finished_ms`. Progressive images are written to the same file while the job runs, and the
/// job's row says it finished before its final image is written; a restart trusts the file only
/// when this marker matches the row (else the job's checkpoint is used).
pub const FINAL_MARKER: &str = "final";

/// Records that `dir/image.exr` is the final image of a job that finished at `finished_ms`.
pub fn write_final_marker(dir: &Path, finished_ms: u64) -> anyhow::Result<()> {
    write_atomic(&dir.join(FINAL_MARKER), finished_ms.to_string().as_bytes())?;
    Ok(())
}

/// Whether `dir/image.exr` is the final image of a job whose row says it finished at
/// `finished_ms`.
pub fn final_image_on_disk(dir: &Path, finished_ms: Option<u64>) -> bool {
    let marker = std::fs::read_to_string(dir.join(FINAL_MARKER)).ok().and_then(|s| s.trim().parse::<u64>().ok());
    finished_ms.is_some() && marker == finished_ms && dir.join("image.exr").is_file()
}

/// A finished single-frame job's images were written (`preview_ev`: its preview's EV): unless
/// it changed since it ended, its film is dropped, its images are served from disk and the final
/// marker says so to a restart. Returns whether they were final.
pub fn final_images_written(state: &AppState, id: JobId, preview_ev: f32) -> bool {
    let Some(finished_ms) = state.farm.lock().final_image_written(id, Some(preview_ev)) else { return false };
    if let Err(e) = write_final_marker(&state.job_dir(id), finished_ms) {
        tracing::error!(job = id, "writing the final image's marker failed: {e:#}");
    }
    if state.farm.lock().job(id).is_err() {
        // Deleted while its images were written: no files may remain.
        state.delete_job_files(id);
    }
    true
}

/// The noisy preview of a frame that has a denoised layer, beside `preview.png`.
pub const NOISY_PREVIEW: &str = "preview-noisy.png";

/// A frame's denoised layer, when it has one.
type Denoised = Option<Arc<Vec<[f32; 3]>>>;

/// A sequence's merged frame: job, index in its frame set, frame number, film, denoised layer.
type FrameToWrite = (JobId, usize, i32, Arc<Film>, Denoised, pathfarm_common::film::PreviewExposure);

type FrameWrite = (
    PathBuf,
    Arc<Film>,
    Denoised,
    pathfarm_common::film::PreviewExposure,
    tokio::sync::oneshot::Sender<anyhow::Result<()>>,
);

/// One thread that resolves and encodes sequence frames, one after the other. A frame's
/// working set (float layers, EXR and PNG buffers: ~100 MiB at 1080p) is then reused frame
/// after frame in one allocator arena; spread over the blocking pool's threads, glibc kept a
/// copy per thread and a 1080p sequence's RSS climbed from 1 to 4.5 GiB over 40 frames.
struct FrameWriter {
    tx: std::sync::mpsc::Sender<FrameWrite>,
}

impl FrameWriter {
    fn start() -> std::io::Result<Self> {
        let (tx, rx) = std::sync::mpsc::channel::<FrameWrite>();
        std::thread::Builder::new().name("frame-writer".into()).spawn(move || {
            for (dir, film, denoised, exposure, reply) in rx {
                let r = (|| -> anyhow::Result<()> {
                    let mut layers = film.resolve();
                    layers.denoised = denoised.map(|d| d.to_vec());
                    let ev = write_outputs(&dir, layers, exposure)?;
                    tracing::debug!(dir = %dir.display(), preview_ev = ev, "frame written");
                    // The frame is written: its checkpoint is of no more use.
                    match std::fs::remove_file(dir.join("checkpoint.bin")) {
                        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e.into()),
                        _ => Ok(()),
                    }
                })();
                drop(film);
                let _ = reply.send(r);
            }
        })?;
        Ok(Self { tx })
    }

    /// Writes `dir/image.exr` and `preview.png` of `film`; `Err` also when the thread is gone.
    async fn write(
        &self,
        dir: PathBuf,
        film: Arc<Film>,
        denoised: Denoised,
        exposure: pathfarm_common::film::PreviewExposure,
    ) -> Result<anyhow::Result<()>, String> {
        let (reply, answer) = tokio::sync::oneshot::channel();
        self.tx
            .send((dir, film, denoised, exposure, reply))
            .map_err(|_| "the frame writer thread is gone".to_string())?;
        answer.await.map_err(|_| "the frame writer thread panicked".to_string())
    }
}

/// Writes each job's EXR and PNG after a pass completes, and always when the job ends. A running
/// job's images are written at most every `output_interval`, and progressive writes of all jobs
/// together take at most ~10% of the time: after one, the next waits nine times as long as it
/// took (a 1024 x 1024 EXR costs ~0.4 s of CPU in ZIP compression, a 4K one four times that;
/// the API serves running jobs' images from their films, so the files on disk may lag a little
/// without anyone waiting on them). Final images and sequence frames are never held back.
pub async fn output_loop(state: Arc<AppState>) {
    let mut next_due: HashMap<JobId, Instant> = HashMap::new();
    let mut progressive_after = Instant::now();
    let writer = match FrameWriter::start() {
        Ok(w) => w,
        Err(e) => {
            tracing::error!("cannot start the frame writer thread: {e}");
            return;
        }
    };
    loop {
        let _ = tokio::time::timeout(Duration::from_millis(500), state.output_ready.notified()).await;
        let (due, frames): (Vec<(JobId, JobState, pathfarm_common::film::PreviewExposure)>, Vec<FrameToWrite>) = {
            let mut farm = state.farm.lock();
            // One progressive write per turn of the budget: the running job written longest ago.
            let now = Instant::now();
            let progressive = if now >= progressive_after {
                farm.jobs()
                    .filter(|j| j.output_due() && !j.sequence && !j.state.is_finished())
                    .filter(|j| next_due.get(&j.id).is_none_or(|t| now >= *t))
                    .min_by_key(|j| next_due.get(&j.id).copied())
                    .map(|j| j.id)
            } else {
                None
            };
            let mut frames = Vec::new();
            let due = farm
                .jobs_mut()
                .filter(|j| j.output_due())
                .filter(|j| j.sequence || j.state.is_finished() || Some(j.id) == progressive)
                .filter_map(|j| {
                    j.output_dirty = false;
                    let exposure = pathfarm_common::film::PreviewExposure::of(&j.settings);
                    if j.sequence {
                        // A frame whose final denoise step is owed is written once it is done.
                        let ready = j.frames_to_write().into_iter().filter(|(i, _, _)| !j.denoise_owed(*i));
                        let with_layer: Vec<FrameToWrite> = ready
                            .map(|(i, f, film)| (j.id, i, f, film, j.denoised(i).map(|d| d.rgb), exposure))
                            .collect();
                        frames.extend(with_layer);
                        None
                    } else {
                        Some((j.id, j.state, exposure))
                    }
                })
                .collect();
            (due, frames)
        };
        // A sequence's merged frames: written once, then their films are dropped.
        for (id, index, frame, film, denoised, exposure) in frames {
            let dir = super::store::frame_dir(&state.job_dir(id), frame);
            match writer.write(dir, film, denoised, exposure).await {
                Ok(Ok(())) => {
                    // Its film is freed: the next frame may start now (the changes say so).
                    let ((written, exists), changes) = state.locked(|farm| {
                        let written = farm.frame_written(id, index).is_some();
                        if let Ok(j) = farm.job_mut(id) {
                            j.drop_denoised(index);
                        }
                        (written, farm.job(id).is_ok())
                    });
                    state.apply_logged(changes, &format!("job {id}'s frame {frame} written"));
                    if written {
                        tracing::info!(job = id, frame, "frame written");
                    } else if !exists {
                        // Deleted while its frame was being written: no files may remain.
                        state.delete_job_files(id);
                    }
                }
                Ok(Err(e)) => {
                    tracing::error!(job = id, frame, "writing the frame's images failed: {e:#}; retrying");
                    if let Ok(j) = state.farm.lock().job_mut(id) {
                        j.output_dirty = true;
                    }
                }
                Err(e) => tracing::error!(job = id, frame, "frame writer panicked: {e}"),
            }
        }
        for (id, job_state, exposure) in due {
            let started = Instant::now();
            let dir = state.job_dir(id);
            let st = state.clone();
            // Resolved band by band, so the farm lock is never held for a whole film.
            let r = tokio::task::spawn_blocking(move || -> anyhow::Result<f32> {
                let layers = resolve_banded(&st, id).map_err(|e| anyhow::anyhow!(e.message))?;
                write_outputs(&dir, layers, exposure)
            })
            .await;
            match r {
                Ok(Ok(ev)) => {
                    tracing::debug!(job = id, state = job_state.as_str(), preview_ev = ev, "images written");
                    if job_state.is_finished() && final_images_written(&state, id, ev) {
                        tracing::debug!(job = id, "film dropped: the job's images are served from its files");
                    }
                }
                Ok(Err(e)) => tracing::error!(job = id, "writing images failed: {e:#}"),
                Err(e) => tracing::error!(job = id, "image writer panicked: {e}"),
            }
            let took = started.elapsed();
            next_due.insert(id, started + state.config.output_interval);
            if !job_state.is_finished() {
                progressive_after = Instant::now() + took * 9;
            }
            state.publish(crate::service::Event::Image { id });
        }
        if next_due.len() > 64 {
            // Jobs gone (deleted, or finished and written) no longer need a turn.
            let farm = state.farm.lock();
            next_due.retain(|id, _| farm.job(*id).is_ok_and(|j| !j.state.is_finished()));
        }
    }
}

/// Rows of the film resolved per hold of the farm lock.
const RESOLVE_BAND_ROWS: usize = 16;

/// Resolves a job's film a band of rows at a time, taking the farm lock once per band: a
/// 1024 x 1024 film takes ~200 ms to resolve, during which leases and merges would wait.
/// Each band copies its sums (splats included) under one lock, so every
/// pixel is consistent; bands may be a few units apart, as tiles are anyway.
pub fn resolve_banded(state: &AppState, id: JobId) -> ServiceResult<ImageLayers> {
    resolve_film_banded(state, id, None)
}

/// The film of job `id` (`frame`: `None` the job's image, `Some(n)` frame `n`), given to `f`.
/// A sequence has no single image (409 pointing at the frame URLs); a frame not started or
/// already written and dropped is 409 too (a written frame is served from its file).
fn with_film<T>(
    farm: &crate::farm::Farm,
    id: JobId,
    frame: Option<i32>,
    f: impl FnOnce(&pathfarm_common::film::Film) -> T,
) -> ServiceResult<T> {
    let job = farm.job(id)?;
    let conflict = |m: String| ServiceError::conflict("no_image", m);
    let no_film = || {
        conflict(if job.state == JobState::Queued {
            format!("job {id} has not started: it has no image before its first unit is leased")
        } else {
            format!("job {id} has no film")
        })
    };
    match frame {
        None if job.sequence => Err(conflict(format!(
            "job {id} is a sequence of {} frames ({}): each frame has its own image at              {API}/jobs/{id}/frames/{{frame}}/image.exr and preview.png; {API}/jobs/{id}/frames lists them",
            job.frames.len(),
            job.frames.spec()
        ))),
        None => job.film().map(|film| f(&film)).ok_or_else(no_film),
        Some(n) if !job.sequence => {
            if job.frames.frames().first() == Some(&n) {
                job.film().map(|film| f(&film)).ok_or_else(no_film)
            } else {
                Err(ServiceError::not_found(format!(
                    "job {id} renders frame {} only, not frame {n}",
                    job.settings.frame
                )))
            }
        }
        Some(n) => {
            let index = job.frame_index(n).ok_or_else(|| {
                ServiceError::not_found(format!("frame {n} is not in job {id}'s frames {}", job.frames.spec()))
            })?;
            match job.frame_film(n) {
                Some(film) => Ok(f(&film)),
                None => {
                    let state = job.frame_info(index).map(|i| i.state);
                    Err(conflict(format!("frame {n} of job {id} has no image in memory (it is {state:?})")))
                }
            }
        }
    }
}

/// Resolves a film a band of rows at a time (see [`resolve_banded`]); `frame` as in `with_film`.
pub fn resolve_film_banded(state: &AppState, id: JobId, frame: Option<i32>) -> ServiceResult<ImageLayers> {
    // A film's size never changes; a frame dropped between bands is refused by `with_film`.
    let (w, h) = {
        let farm = state.farm.lock();
        with_film(&farm, id, frame, |f| (f.width as usize, f.height as usize))?
    };
    let n = w * h;
    let mut out = ImageLayers {
        width: w as u32,
        height: h as u32,
        rgb: Vec::with_capacity(n),
        albedo: Vec::with_capacity(n),
        normal: Vec::with_capacity(n),
        depth: Vec::with_capacity(n),
        samples: Vec::with_capacity(n),
        variance: Vec::with_capacity(n),
        denoised: None,
    };
    let mut y0 = 0;
    while y0 < h {
        let y1 = (y0 + RESOLVE_BAND_ROWS).min(h);
        let band = {
            let farm = state.farm.lock();
            with_film(&farm, id, frame, |f| f.band(y0 as u32, y1 as u32))?
        };
        let r = band.resolve();
        out.rgb.extend(r.rgb);
        out.albedo.extend(r.albedo);
        out.normal.extend(r.normal);
        out.depth.extend(r.depth);
        out.samples.extend(r.samples);
        out.variance.extend(r.variance);
        y0 = y1;
    }
    // The newest denoised layer the farm holds for the frame (`farm/denoise.rs`).
    out.denoised = {
        let farm = state.farm.lock();
        let job = farm.job(id)?;
        let index = match frame {
            Some(n) => job.frame_index(n),
            None => Some(0),
        };
        index.and_then(|i| job.denoised(i)).map(|d| d.rgb.to_vec())
    };
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::farm::tests::fake_result;
    use pathfarm_common::job::RenderSettings;

    /// Leases and merges `n` units as worker `w` (of the one job there is), applying the farm's
    /// changes as the service does (a completed job's row is written at once).
    fn merge_units(state: &AppState, w: u64, n: usize) {
        for _ in 0..n {
            let changes = state.locked(|farm| {
                let g = farm.lease(w, 0).expect("lease").expect("work");
                farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
            });
            state.apply(changes.1).expect("apply");
        }
    }

    /// The coordinator killed after a job completed (its row says so) but before its last
    /// checkpoint and its final image: the image on disk is a progressive one and the
    /// checkpoint lacks the last units. The restart renders those units again (the job is not
    /// completed with the progressive image, as it was); once the final image and its marker
    /// are written, a restart serves it from disk.
    #[test]
    fn a_progressive_image_is_not_taken_for_the_final_one_after_a_restart() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
        let mut s = RenderSettings::new(16, 16, 4);
        s.tile_size = 8;
        let units = s.plan().unit_count();
        let id = {
            let state = AppState::new(cfg.clone()).expect("state");
            let id = state.farm.lock().submit("s".into(), None, 0, s.clone(), 0).expect("submit");
            let w = state.farm.lock().register("w".into(), 1, 0);
            merge_units(&state, w, units - 2);
            assert_eq!(super::super::loops::checkpoint_all(&state), 1);
            // A progressive write, as the output loop makes while the job runs.
            let layers = resolve_banded(&state, id).expect("film");
            write_outputs(&state.job_dir(id), layers, Default::default()).expect("progressive image");
            merge_units(&state, w, 2);
            assert_eq!(state.farm.lock().job(id).expect("job").state, JobState::Completed);
            id
        };
        let state = AppState::new(cfg.clone()).expect("restart");
        {
            let farm = state.farm.lock();
            let job = farm.job(id).expect("job");
            assert_eq!((job.state, job.units_merged), (JobState::Queued, units as u64 - 2));
            assert!(job.image_on_disk().is_none(), "the progressive image was taken for the final one");
        }
        assert!(super::super::residency::apply_residency(&state));
        let w = state.farm.lock().register("w".into(), 1, 0);
        merge_units(&state, w, 2);
        assert_eq!(state.farm.lock().job(id).expect("job").state, JobState::Completed);
        assert!(state.farm.lock().lease(w, 0).expect("lease").is_none());
        // The output loop's final write (it takes the job's dirty flag when it starts one).
        state.farm.lock().job_mut(id).expect("job").output_dirty = false;
        let ev = write_outputs(&state.job_dir(id), resolve_banded(&state, id).expect("film"), Default::default())
            .expect("final image");
        assert!(final_images_written(&state, id, ev));
        drop(state);
        let state = AppState::new(cfg).expect("second restart");
        let farm = state.farm.lock();
        let job = farm.job(id).expect("job");
        assert_eq!((job.state, job.units_merged), (JobState::Completed, units as u64));
        assert!(job.image_on_disk().is_some(), "the final image is served from disk");
    }
}
