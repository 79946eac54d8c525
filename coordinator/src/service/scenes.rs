//! Content-addressed scene bundles on disk, and their garbage collection.

use super::*;

/// What the scene store remembers about a bundle.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneMeta {
    pub triangles: usize,
    pub cameras: usize,
    pub warnings: Vec<String>,
}

/// Content-addressed scene bundles under `data_dir/scenes`.
pub struct SceneStore {
    dir: PathBuf,
    /// Per scene: its meta and when it was stored (Unix ms; the bundle's modification time
    /// after a restart, refreshed when the same bytes are uploaded again).
    meta: Mutex<HashMap<String, (SceneMeta, u64)>>,
}

impl SceneStore {
    pub(super) fn open(dir: PathBuf) -> std::io::Result<Self> {
        std::fs::create_dir_all(&dir)?;
        let mut meta = HashMap::new();
        for entry in std::fs::read_dir(&dir)? {
            let path = entry?.path();
            let Some(id) = path.file_stem().and_then(|s| s.to_str()) else { continue };
            if path.extension().is_some_and(|e| e == "json")
                && is_scene_id(id)
                && let Some(m) = std::fs::read(&path).ok().and_then(|b| serde_json::from_slice(&b).ok())
            {
                let stored = std::fs::metadata(dir.join(format!("{id}.bundle")))
                    .and_then(|m| m.modified())
                    .ok()
                    .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
                    .map_or_else(now_ms, |d| d.as_millis() as u64);
                meta.insert(id.to_string(), (m, stored));
            }
        }
        Ok(Self { dir, meta: Mutex::new(meta) })
    }

    pub fn bundle_path(&self, id: &str) -> PathBuf {
        self.dir.join(format!("{id}.bundle"))
    }

    fn entries(&self) -> MutexGuard<'_, HashMap<String, (SceneMeta, u64)>> {
        self.meta.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn meta(&self, id: &str) -> Option<SceneMeta> {
        self.entries().get(id).map(|(m, _)| m.clone())
    }

    /// Forgets a scene and removes its bundle and meta file; `Ok(false)` when it was not stored.
    /// Callers hold the farm lock, so no job can be submitted for the scene meanwhile
    /// (`create_job` checks the scene again under that lock).
    pub fn remove(&self, id: &str) -> std::io::Result<bool> {
        if self.entries().remove(id).is_none() {
            return Ok(false);
        }
        for path in [self.bundle_path(id), self.dir.join(format!("{id}.json"))] {
            match std::fs::remove_file(&path) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(e),
                _ => {}
            }
        }
        tracing::info!(scene = %id, "scene removed");
        Ok(true)
    }

    /// Scenes stored at or before `stored_before` (Unix ms) that `referenced` does not name.
    pub fn unreferenced_before(&self, stored_before: u64, referenced: &dyn Fn(&str) -> bool) -> Vec<String> {
        self.entries()
            .iter()
            .filter(|(id, (_, stored))| *stored <= stored_before && !referenced(id))
            .map(|(id, _)| id.clone())
            .collect()
    }

    /// Validates (by loading) and stores a bundle; idempotent for the same bytes.
    pub fn add(&self, bytes: &[u8], opts: &LoadOptions) -> ServiceResult<SceneCreated> {
        let id = scene_id(bytes);
        if let Some((m, stored)) = self.entries().get_mut(&id) {
            // Uploaded again: the client is about to use it, so the GC's clock starts over
            // (also across a restart, through the bundle's modification time).
            *stored = now_ms();
            let m = m.clone();
            if let Err(e) = std::fs::File::options()
                .append(true)
                .open(self.bundle_path(&id))
                .and_then(|f| f.set_modified(SystemTime::now()))
            {
                tracing::warn!(scene = %id, error = %e, "refreshing the scene's modification time failed");
            }
            return Ok(SceneCreated { scene_id: id, triangles: m.triangles, warnings: m.warnings });
        }
        // A scratch folder per upload: concurrent uploads of the same bytes must not share one.
        static SCRATCH_SEQ: AtomicU64 = AtomicU64::new(0);
        let seq = SCRATCH_SEQ.fetch_add(1, Ordering::Relaxed);
        let scratch = self.dir.join(format!(".unpack-{id}-{}-{seq}", std::process::id()));
        let loaded = match unpack_bundle(bytes, &scratch) {
            Ok(main) => load_scene(&main, opts),
            // Unpacking writes on our disk: its I/O errors are ours, not the client's.
            Err(pathfarm_common::scene::SceneError::Io { source, .. }) => {
                let _ = std::fs::remove_dir_all(&scratch);
                return Err(storage_error(&source, "the scene"));
            }
            Err(e) => Err(e),
        };
        let _ = std::fs::remove_dir_all(&scratch);
        let scene = loaded.map_err(|e| {
            use pathfarm_common::scene::SceneError;
            match e {
                SceneError::LimitExceeded { .. } => ServiceError::unprocessable("limit_exceeded", e.to_string()),
                SceneError::ForbiddenUri { .. } => ServiceError::unprocessable("forbidden_uri", e.to_string()),
                _ => ServiceError::unprocessable("invalid_scene", e.to_string()),
            }
        })?;
        let meta =
            SceneMeta { triangles: scene.triangle_count(), cameras: scene.cameras.len(), warnings: scene.warnings };
        let io = |e: pathfarm_common::film::ImageError| match e {
            pathfarm_common::film::ImageError::Io { source, .. } => storage_error(&source, "the scene"),
            _ => ServiceError::internal("storing the scene failed"),
        };
        write_atomic(&self.bundle_path(&id), bytes).map_err(io)?;
        let meta_json = serde_json::to_vec(&meta).map_err(|e| ServiceError::internal(e.to_string()))?;
        write_atomic(&self.dir.join(format!("{id}.json")), &meta_json).map_err(io)?;
        tracing::info!(scene = %id, triangles = meta.triangles, "scene stored");
        self.entries().insert(id.clone(), (meta.clone(), now_ms()));
        Ok(SceneCreated { scene_id: id, triangles: meta.triangles, warnings: meta.warnings })
    }
}

/// Removes the scenes stored at or before `stored_before` (Unix ms) that no job, in any state,
/// references. The farm lock is held throughout, so no job can be submitted for a scene being
/// removed. Returns the removed ids.
pub fn collect_scenes(state: &AppState, stored_before: u64) -> Vec<String> {
    let farm = state.farm.lock();
    let referenced = |id: &str| farm.jobs().any(|j| j.scene_id == id);
    let mut removed = Vec::new();
    for id in state.scenes.unreferenced_before(stored_before, &referenced) {
        match state.scenes.remove(&id) {
            Ok(_) => {
                tracing::info!(scene = %id, "unreferenced scene garbage-collected");
                removed.push(id);
            }
            Err(e) => tracing::error!(scene = %id, error = %e, "removing an unreferenced scene failed"),
        }
    }
    removed
}
