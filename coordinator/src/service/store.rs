//! Durable state under `--data-dir`: SQLite (WAL) for jobs and workers, and per-job checkpoint
//! files holding the film together with the set of merged units.
//!
//! A checkpoint is one file written atomically (temp file + rename) with a CRC-32, so a crash
//! leaves either the old or the new checkpoint, never a torn one. On start the coordinator
//! restores every job from its row and last checkpoint; units merged after that checkpoint are
//! pending again and will be rendered and merged once more, into a film that does not hold them.

use crate::farm::{Checkpoint, CheckpointHead, JobRecord};
use anyhow::{Context, bail};
use pathfarm_common::film::{Film, PIXEL_BYTES, write_atomic_with};
use pathfarm_common::frames::FrameSet;
use pathfarm_common::job::RenderSettings;
use pathfarm_common::protocol::{
    Codec, FrameOrder, JobId, JobState, Notify, max_section_bytes, push_pixels, read_pixels,
};
use rusqlite::{Connection, OptionalExtension, params};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

const CHECKPOINT_MAGIC: &[u8; 4] = b"PFC2";

/// The SQLite database and the checkpoint folder.
pub struct Store {
    conn: Connection,
    jobs_dir: PathBuf,
}

fn state_from_str(s: &str) -> anyhow::Result<JobState> {
    Ok(match s {
        "queued" => JobState::Queued,
        "running" => JobState::Running,
        "paused" => JobState::Paused,
        "completed" => JobState::Completed,
        "failed" => JobState::Failed,
        "cancelled" => JobState::Cancelled,
        other => bail!("unknown job state {other:?} in the database"),
    })
}

/// Schema migrations, applied in order by `rusqlite_migration`, which keeps the number applied
/// in SQLite's `PRAGMA user_version`. Append new ones; never edit one that has shipped.
///
/// Migration 1 is the schema of the versions before migrations. Those made their tables with
/// `CREATE TABLE IF NOT EXISTS` and left `user_version` at 0, so it keeps `IF NOT EXISTS` and
/// its hook adds the columns that databases older still lack: it adopts such a database with its
/// rows, and creates a fresh one.
fn migrations() -> rusqlite_migration::Migrations<'static> {
    use rusqlite_migration::{HookResult, M, Migrations};
    fn add_missing_columns(tx: &rusqlite::Transaction<'_>) -> HookResult {
        let has = |col: &str| tx.prepare(&format!("SELECT {col} FROM jobs LIMIT 0")).is_ok();
        // Databases of versions before worker tags lack `requires`, ...
        if !has("requires") {
            tx.execute_batch("ALTER TABLE jobs ADD COLUMN requires TEXT NOT NULL DEFAULT '[]'")?;
        }
        // ... those before webhooks lack `notify` (JSON of the job's `notify`, or NULL), ...
        if !has("notify") {
            tx.execute_batch("ALTER TABLE jobs ADD COLUMN notify TEXT")?;
        }
        // ... and those before sequences lack `frames` (NULL: one frame) and `frame_order`.
        if !has("frames") {
            tx.execute_batch(
                "ALTER TABLE jobs ADD COLUMN frames TEXT; ALTER TABLE jobs ADD COLUMN frame_order TEXT NOT NULL DEFAULT 'frame'",
            )?;
        }
        Ok(())
    }
    Migrations::new(vec![M::up_with_hook(
        "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
         CREATE TABLE IF NOT EXISTS jobs (
             id INTEGER PRIMARY KEY,
             name TEXT NOT NULL,
             scene_id TEXT NOT NULL,
             priority INTEGER NOT NULL,
             settings TEXT NOT NULL,
             state TEXT NOT NULL,
             created_ms INTEGER NOT NULL,
             finished_ms INTEGER,
             error TEXT,
             run_ms INTEGER NOT NULL DEFAULT 0,
             requires TEXT NOT NULL DEFAULT '[]',
             notify TEXT,
             frames TEXT,
             frame_order TEXT NOT NULL DEFAULT 'frame'
         );
         CREATE TABLE IF NOT EXISTS workers (
             id INTEGER PRIMARY KEY,
             name TEXT NOT NULL,
             threads INTEGER NOT NULL,
             registered_ms INTEGER NOT NULL
         );",
        add_missing_columns,
    )])
}

/// The schema version this build writes: the number of migrations.
pub const SCHEMA_VERSION: usize = 1;

/// Brings the database to [`SCHEMA_VERSION`]; refuses one written by a newer version (a higher
/// `user_version`) untouched, since this build cannot know what its schema means.
fn migrate(conn: &mut Connection) -> anyhow::Result<()> {
    let found: i64 = conn.pragma_query_value(None, "user_version", |r| r.get(0))?;
    if found > SCHEMA_VERSION as i64 {
        bail!(
            "the database has schema version {found}, newer than this coordinator's {SCHEMA_VERSION}: \
             it was written by a newer pathfarm; run that version, or start this one with another --data-dir"
        );
    }
    migrations().to_latest(conn)?;
    Ok(())
}

impl Store {
    /// Opens (creating if needed) `data_dir/pathfarm.db`.
    pub fn open(data_dir: &Path) -> anyhow::Result<Self> {
        let path = data_dir.join("pathfarm.db");
        let mut conn = Connection::open(&path).with_context(|| format!("opening {}", path.display()))?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        // FULL: a transaction is on disk before the API acknowledges it (NORMAL in WAL mode may
        // lose the last commits on power loss).
        conn.pragma_update(None, "synchronous", "FULL")?;
        migrate(&mut conn).with_context(|| format!("migrating {}", path.display()))?;
        let jobs_dir = data_dir.join("jobs");
        std::fs::create_dir_all(&jobs_dir)?;
        Ok(Self { conn, jobs_dir })
    }

    /// Counts this start and returns the new epoch (1 on the first start).
    pub fn next_epoch(&self) -> anyhow::Result<u64> {
        let old: Option<i64> =
            self.conn.query_row("SELECT value FROM meta WHERE key = 'epoch'", [], |r| r.get(0)).optional()?;
        let epoch = old.unwrap_or(0) + 1;
        self.conn.execute(
            "INSERT INTO meta (key, value) VALUES ('epoch', ?1) ON CONFLICT(key) DO UPDATE SET value = ?1",
            params![epoch],
        )?;
        Ok(epoch as u64)
    }

    pub fn put_job(&self, r: &JobRecord) -> anyhow::Result<()> {
        self.conn.execute(
            "INSERT INTO jobs (id, name, scene_id, priority, settings, state, created_ms, finished_ms, error, run_ms, requires, notify, frames, frame_order)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14)
             ON CONFLICT(id) DO UPDATE SET name = ?2, priority = ?4, state = ?6, finished_ms = ?8, error = ?9, run_ms = ?10",
            params![
                r.id as i64,
                r.name,
                r.scene_id,
                r.priority,
                serde_json::to_string(&r.settings)?,
                r.state.as_str(),
                r.created_ms as i64,
                r.finished_ms.map(|v| v as i64),
                r.error,
                r.run_ms as i64,
                serde_json::to_string(&r.requires)?,
                r.notify.as_ref().map(serde_json::to_string).transpose()?,
                r.frames.as_ref().map(|f| f.spec().to_string()),
                r.order.as_str(),
            ],
        )?;
        Ok(())
    }

    /// Refuses every later write (tests: a disk that stopped taking writes).
    #[cfg(test)]
    pub fn refuse_writes(&self) {
        let _ = self.conn.pragma_update(None, "query_only", "ON");
    }

    /// The highest job id ever written (deleted jobs and rows `jobs` skips included), 0 if none.
    pub fn max_job_id(&self) -> anyhow::Result<JobId> {
        let v: Option<i64> =
            self.conn.query_row("SELECT value FROM meta WHERE key = 'max_job_id'", [], |r| r.get(0)).optional()?;
        let rows: Option<i64> = self.conn.query_row("SELECT MAX(id) FROM jobs", [], |r| r.get(0))?;
        Ok(v.unwrap_or(0).max(rows.unwrap_or(0)).max(0) as JobId)
    }

    pub fn delete_job(&self, id: JobId) -> anyhow::Result<()> {
        // Remember the id, so a restart never hands it out again.
        self.conn.execute(
            "INSERT INTO meta (key, value) VALUES ('max_job_id', ?1)
             ON CONFLICT(key) DO UPDATE SET value = MAX(value, excluded.value)",
            params![id as i64],
        )?;
        self.conn.execute("DELETE FROM jobs WHERE id = ?1", params![id as i64])?;
        Ok(())
    }

    pub fn jobs(&self) -> anyhow::Result<Vec<JobRecord>> {
        let mut stmt = self.conn.prepare(
            "SELECT id, name, scene_id, priority, settings, state, created_ms, finished_ms, error, run_ms, requires, notify, frames, frame_order FROM jobs ORDER BY id",
        )?;
        let rows = stmt.query_map([], |r| {
            Ok((
                r.get::<_, i64>(0)?,
                r.get::<_, String>(1)?,
                r.get::<_, String>(2)?,
                r.get::<_, i32>(3)?,
                r.get::<_, String>(4)?,
                r.get::<_, String>(5)?,
                r.get::<_, i64>(6)?,
                r.get::<_, Option<i64>>(7)?,
                r.get::<_, Option<String>>(8)?,
                r.get::<_, i64>(9)?,
                r.get::<_, String>(10)?,
                r.get::<_, Option<String>>(11)?,
                r.get::<_, Option<String>>(12)?,
                r.get::<_, String>(13)?,
            ))
        })?;
        let mut out = Vec::new();
        for (i, row) in rows.enumerate() {
            // One damaged row (a state this version does not know, settings that do not parse,
            // a column of the wrong type) must not stop the coordinator: skip it, loudly.
            let (
                id,
                name,
                scene_id,
                priority,
                settings,
                state,
                created,
                finished,
                error,
                run_ms,
                requires,
                notify,
                frames,
                order,
            ) = match row {
                Ok(r) => r,
                Err(e) => {
                    tracing::warn!(row = i, "skipping an unreadable job row in the database: {e}");
                    continue;
                }
            };
            let parsed = serde_json::from_str::<RenderSettings>(&settings)
                .map_err(|e| anyhow::anyhow!("settings do not parse: {e}"))
                .and_then(|settings| {
                    let requires = serde_json::from_str::<Vec<String>>(&requires)
                        .map_err(|e| anyhow::anyhow!("requires does not parse: {e}"))?;
                    let notify = notify
                        .map(|n| serde_json::from_str::<Notify>(&n))
                        .transpose()
                        .map_err(|e| anyhow::anyhow!("notify does not parse: {e}"))?;
                    let frames = frames
                        .map(|f| FrameSet::parse(&f))
                        .transpose()
                        .map_err(|e| anyhow::anyhow!("frames do not parse: {e}"))?;
                    let order = match order.as_str() {
                        "frame" => FrameOrder::Frame,
                        "sequence_preview" => FrameOrder::SequencePreview,
                        other => bail!("unknown frame order {other:?}"),
                    };
                    Ok((settings, state_from_str(&state)?, requires, notify, frames, order))
                });
            let (settings, state, requires, notify, frames, order) = match parsed {
                Ok(p) => p,
                Err(e) => {
                    tracing::warn!(job = id, "skipping job {id} from the database: {e:#}");
                    continue;
                }
            };
            out.push(JobRecord {
                id: id as u64,
                name,
                scene_id,
                priority,
                settings,
                requires,
                notify,
                frames,
                order,
                state,
                created_ms: created as u64,
                finished_ms: finished.map(|v| v as u64),
                error,
                run_ms: run_ms as u64,
            });
        }
        Ok(out)
    }

    pub fn put_worker(&self, id: u64, name: &str, threads: u32, registered_ms: u64) -> anyhow::Result<()> {
        self.conn.execute(
            "INSERT OR REPLACE INTO workers (id, name, threads, registered_ms) VALUES (?1, ?2, ?3, ?4)",
            params![id as i64, name, threads, registered_ms as i64],
        )?;
        Ok(())
    }

    /// Deletes the rows of pruned workers.
    pub fn delete_workers(&self, ids: &[u64]) -> anyhow::Result<()> {
        for id in ids {
            self.conn.execute("DELETE FROM workers WHERE id = ?1", params![*id as i64])?;
        }
        Ok(())
    }

    /// Deletes the rows of workers registered before `before_ms` (on start: workers of earlier
    /// runs register again, their rows only grow the table).
    pub fn delete_workers_registered_before(&self, before_ms: u64) -> anyhow::Result<usize> {
        Ok(self.conn.execute("DELETE FROM workers WHERE registered_ms < ?1", params![before_ms as i64])?)
    }

    pub fn checkpoint_path(&self, id: JobId) -> PathBuf {
        self.jobs_dir.join(id.to_string()).join("checkpoint.bin")
    }

    /// Where a sequence's checkpoint of `frame` lives (beside its images).
    pub fn frame_checkpoint_path(&self, id: JobId, frame: i32) -> PathBuf {
        frame_dir(&self.jobs_dir.join(id.to_string()), frame).join("checkpoint.bin")
    }

    /// A sequence's frames on disk: the indices (in `frames`) of frames whose `image.exr` is
    /// written, and the checkpoint heads of the others (their films stay on disk until
    /// leased). Reads the job's `frames/` folder once.
    pub fn sequence_state(&self, id: JobId, frames: &FrameSet) -> (Vec<usize>, Vec<CheckpointHead>) {
        let dir = self.jobs_dir.join(id.to_string()).join("frames");
        let index: std::collections::HashMap<i32, usize> =
            frames.frames().iter().enumerate().map(|(i, &f)| (f, i)).collect();
        let (mut done, mut checkpoints) = (Vec::new(), Vec::new());
        let Ok(entries) = std::fs::read_dir(&dir) else { return (done, checkpoints) };
        for entry in entries.flatten() {
            let Some(frame) = entry.file_name().to_str().and_then(|n| n.parse::<i32>().ok()) else { continue };
            let Some(&i) = index.get(&frame) else { continue };
            let path = entry.path();
            if path.join("image.exr").is_file() {
                done.push(i);
                // A checkpoint written after the frame's images is stale.
                let _ = std::fs::remove_file(path.join("checkpoint.bin"));
            } else if let Some(cp) = read_checkpoint_head(&path.join("checkpoint.bin")) {
                checkpoints.push(cp);
            }
        }
        done.sort_unstable();
        (done, checkpoints)
    }
}

/// The folder of frame `frame` of a sequence job whose folder is `job_dir`: `frames/NNNN`
/// (`frames/-007` for frame -7).
pub fn frame_dir(job_dir: &Path, frame: i32) -> PathBuf {
    job_dir.join(pathfarm_common::frames::frame_path("frames/####", frame))
}

impl Store {}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CheckpointHeader {
    job_id: JobId,
    /// The frame number.
    frame: i32,
    width: u32,
    height: u32,
    /// Bytes per pixel of the film sections.
    pixel_bytes: u32,
    next_pass: Vec<u32>,
}

/// Pixels per film section of a checkpoint (64 MiB: lz4 blocks stay far below their 4 GiB limit).
const CHECKPOINT_CHUNK_PIXELS: usize = 1 << 20;

/// Encodes a checkpoint: magic, JSON header, the film's pixels in lz4 sections of at most
/// `CHECKPOINT_CHUNK_PIXELS` ([`PixelSums::write_le`](pathfarm_common::film::PixelSums::write_le)
/// layout), CRC-32.
pub fn encode_checkpoint(cp: &Checkpoint) -> Vec<u8> {
    let mut out = Vec::new();
    // Writing to a Vec cannot fail.
    let _ = write_checkpoint_to(&mut out, cp);
    out
}

/// [`encode_checkpoint`] written to `w` one section at a time, its CRC computed on the way: a
/// 4K film's checkpoint is never held in memory whole (one section, 64 MiB, at a time).
fn write_checkpoint_to(w: &mut impl std::io::Write, cp: &Checkpoint) -> std::io::Result<()> {
    let header = CheckpointHeader {
        job_id: cp.job_id,
        frame: cp.frame,
        width: cp.film.width,
        height: cp.film.height,
        pixel_bytes: PIXEL_BYTES as u32,
        next_pass: cp.next_pass.clone(),
    };
    let header = serde_json::to_vec(&header).unwrap_or_default();
    let mut crc = crc32fast::Hasher::new();
    let mut put = |w: &mut dyn std::io::Write, bytes: &[u8]| {
        crc.update(bytes);
        w.write_all(bytes)
    };
    put(w, CHECKPOINT_MAGIC)?;
    put(w, &(header.len() as u32).to_le_bytes())?;
    put(w, &header)?;
    let mut section = Vec::new();
    for chunk in cp.film.sums.chunks(CHECKPOINT_CHUNK_PIXELS) {
        section.clear();
        push_pixels(&mut section, chunk, Codec::Lz4);
        put(w, &section)?;
    }
    w.write_all(&crc.finalize().to_le_bytes())
}

/// Decodes and verifies a checkpoint. One of an older coordinator (`PFC1`: 13 x 128-bit sums per
/// pixel) is refused with an error that says so.
pub fn decode_checkpoint(bytes: &[u8]) -> anyhow::Result<Checkpoint> {
    decode_checkpoint_from(bytes)
}

/// Reads and verifies the checkpoint at `path`, one section at a time (the file is never held
/// in memory whole: a 4K film's is hundreds of MB).
pub fn load_checkpoint(path: &Path) -> anyhow::Result<Checkpoint> {
    let f = std::fs::File::open(path).with_context(|| format!("reading {}", path.display()))?;
    decode_checkpoint_from(std::io::BufReader::with_capacity(1 << 20, f))
}

/// [`decode_checkpoint`] from a reader: header, then each section read, checked against its
/// bound before anything is allocated, and decoded into the film; the CRC is checked at the end,
/// and nothing may follow it.
fn decode_checkpoint_from(mut r: impl std::io::Read) -> anyhow::Result<Checkpoint> {
    let mut crc = crc32fast::Hasher::new();
    let mut take = |r: &mut dyn std::io::Read, buf: &mut [u8], what: &str| -> anyhow::Result<()> {
        r.read_exact(buf).with_context(|| format!("checkpoint truncated in its {what}"))?;
        crc.update(buf);
        Ok(())
    };
    let mut start = [0u8; 8];
    take(&mut r, &mut start[..4], "magic").context("not a checkpoint")?;
    if &start[..4] == b"PFC1" {
        bail!(
            "a checkpoint of the PFC1 format (128-bit sums) of an older coordinator is not read: the frame renders again from zero"
        );
    }
    if &start[..4] != CHECKPOINT_MAGIC {
        bail!("not a checkpoint");
    }
    take(&mut r, &mut start[4..], "header length")?;
    let hlen = u32::from_le_bytes([start[4], start[5], start[6], start[7]]) as usize;
    if hlen > 64 << 20 {
        bail!("checkpoint header of {hlen} bytes");
    }
    let mut header = vec![0u8; hlen];
    take(&mut r, &mut header, "header")?;
    let h: CheckpointHeader = serde_json::from_slice(&header)?;
    if h.pixel_bytes != PIXEL_BYTES as u32 {
        bail!("checkpoint has {} bytes per pixel, this coordinator {PIXEL_BYTES}", h.pixel_bytes);
    }
    let mut film = Film::new(h.width, h.height);
    let mut section = Vec::new();
    for chunk in film.sums.chunks_mut(CHECKPOINT_CHUNK_PIXELS) {
        let mut prefix = [0u8; 9];
        take(&mut r, &mut prefix, "film")?;
        let len = u64::from_le_bytes(prefix[1..9].try_into().unwrap_or_default());
        let bound = max_section_bytes((chunk.len() * PIXEL_BYTES) as u64);
        if len > bound {
            bail!("checkpoint section of {len} bytes for {} pixels", chunk.len());
        }
        section.clear();
        section.extend_from_slice(&prefix);
        section.resize(9 + len as usize, 0);
        take(&mut r, &mut section[9..], "film")?;
        let mut rest = section.as_slice();
        let pixels = read_pixels(&mut rest, chunk.len(), "film")?;
        chunk.copy_from_slice(&pixels);
    }
    let expected = crc.finalize();
    let mut stored = [0u8; 4];
    r.read_exact(&mut stored).context("checkpoint truncated before its checksum")?;
    if u32::from_le_bytes(stored) != expected {
        bail!("checkpoint checksum mismatch");
    }
    if r.read(&mut [0u8; 1])? != 0 {
        bail!("checkpoint has trailing bytes");
    }
    Ok(Checkpoint { job_id: h.job_id, frame: h.frame, next_pass: h.next_pass, film })
}

/// Reads only the header of a checkpoint (the frame's merged set, not its film), if there is
/// one that this coordinator can read; the film is read (and its checksum checked) by
/// [`read_checkpoint`] when the frame is leased again.
pub fn read_checkpoint_head(path: &Path) -> Option<CheckpointHead> {
    use std::io::Read;
    let head = (|| -> anyhow::Result<Option<CheckpointHead>> {
        let mut f = match std::fs::File::open(path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e.into()),
        };
        let mut start = [0u8; 8];
        f.read_exact(&mut start)?;
        if &start[..4] != CHECKPOINT_MAGIC {
            bail!("not a checkpoint of this coordinator (magic {:?})", String::from_utf8_lossy(&start[..4]));
        }
        let hlen = u32::from_le_bytes([start[4], start[5], start[6], start[7]]) as usize;
        if hlen > 64 << 20 {
            bail!("checkpoint header of {hlen} bytes");
        }
        let mut header = vec![0u8; hlen];
        f.read_exact(&mut header)?;
        let h: CheckpointHeader = serde_json::from_slice(&header)?;
        if h.pixel_bytes != PIXEL_BYTES as u32 {
            bail!("checkpoint has {} bytes per pixel, this coordinator {PIXEL_BYTES}", h.pixel_bytes);
        }
        Ok(Some(CheckpointHead {
            job_id: h.job_id,
            frame: h.frame,
            width: h.width,
            height: h.height,
            next_pass: h.next_pass,
        }))
    })();
    head.unwrap_or_else(|e| {
        tracing::error!(path = %path.display(), "ignoring a checkpoint that cannot be read (damaged or of an older format): {e:#}");
        None
    })
}

/// Writes a checkpoint atomically.
pub fn write_checkpoint(path: &Path, cp: &Checkpoint) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    write_atomic_with(path, |w| write_checkpoint_to(w, cp))?;
    Ok(())
}

/// Reads a checkpoint if there is one; a damaged one is reported and ignored (the job restarts
/// from zero rather than from wrong sums).
pub fn read_checkpoint(path: &Path) -> Option<Checkpoint> {
    if !path.exists() {
        return None;
    }
    match load_checkpoint(path) {
        Ok(cp) => Some(cp),
        Err(e) => {
            tracing::error!(path = %path.display(), "ignoring a checkpoint that cannot be read (damaged or of an older format): {e:#}");
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_common::protocol::NotifyEvent;

    #[test]
    fn checkpoint_roundtrip_and_corruption() {
        let mut film = Film::new(5, 3);
        film.sums[7].rgb[1] = 123_456_789_012_345;
        film.sums[7].weight = 4;
        film.sums[2].albedo = [1, 2, 3];
        let cp = Checkpoint { job_id: 4, frame: -7, next_pass: vec![1, 2], film };
        let bytes = encode_checkpoint(&cp);
        assert_eq!(decode_checkpoint(&bytes).expect("decode"), cp);
        // The head alone is read without the film.
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("checkpoint.bin");
        write_checkpoint(&path, &cp).expect("write");
        assert_eq!(read_checkpoint_head(&path), Some(cp.head()));
        assert_eq!(read_checkpoint_head(&dir.path().join("none.bin")), None);
        let mut bad = bytes.clone();
        bad[20] ^= 1;
        assert!(decode_checkpoint(&bad).is_err());
        assert!(decode_checkpoint(&bytes[..bytes.len() - 1]).is_err());
        // A checkpoint of the old format is refused, saying why.
        let mut old = bytes.clone();
        old[..4].copy_from_slice(b"PFC1");
        let e = decode_checkpoint(&old).expect_err("PFC1");
        assert!(e.to_string().contains("PFC1 format"), "{e}");
    }

    /// A film of two sections is written section by section and read back the same way: the file
    /// is `encode_checkpoint`'s bytes; damage anywhere, a section declaring more than its bound,
    /// a missing end or trailing bytes are refused.
    #[test]
    fn checkpoints_stream_section_by_section() {
        let (w, h) = (1025, 1024);
        let mut film = Film::new(w, h);
        for (i, p) in film.sums.iter_mut().enumerate().step_by(997) {
            p.rgb = [i as u64, 3 * i as u64, 7];
            p.weight = i as u32 % 9;
        }
        let cp = Checkpoint { job_id: 9, frame: 2, next_pass: vec![3; 17], film };
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("checkpoint.bin");
        write_checkpoint(&path, &cp).expect("write");
        let bytes = std::fs::read(&path).expect("read");
        assert!(bytes == encode_checkpoint(&cp), "the streamed file differs from the encoded checkpoint");
        assert!(load_checkpoint(&path).expect("load") == cp);
        for at in [9, bytes.len() / 2, bytes.len() - 5] {
            let mut bad = bytes.clone();
            bad[at] ^= 0x10;
            assert!(decode_checkpoint(&bad).is_err(), "damage at byte {at} not found");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(decode_checkpoint(&longer).expect_err("trailing").to_string().contains("trailing"));
        assert!(decode_checkpoint(&bytes[..bytes.len() - 4]).is_err());
        // The first section's declared length, far beyond its bound: refused before reading it.
        let hlen = u32::from_le_bytes(bytes[4..8].try_into().expect("4 bytes")) as usize;
        let mut huge = bytes.clone();
        huge[8 + hlen + 1..8 + hlen + 9].copy_from_slice(&(1u64 << 40).to_le_bytes());
        let e = decode_checkpoint(&huge).expect_err("huge section");
        assert!(e.to_string().contains("section of"), "{e}");
    }

    #[test]
    fn jobs_survive_reopening_and_epochs_count_up() {
        let dir = tempfile::tempdir().expect("tempdir");
        let rec = JobRecord {
            id: 3,
            name: "n".into(),
            scene_id: "s".into(),
            priority: 2,
            settings: RenderSettings::new(8, 8, 4),
            requires: vec!["highmem".into()],
            notify: Some(Notify {
                url: "https://example.com/hook?job=3".into(),
                events: vec![NotifyEvent::Completed, NotifyEvent::Failed],
            }),
            frames: Some(FrameSet::parse("1-10x3,40").expect("frames")),
            order: FrameOrder::SequencePreview,
            state: JobState::Running,
            created_ms: 10,
            finished_ms: None,
            error: None,
            run_ms: 77,
        };
        {
            let store = Store::open(dir.path()).expect("open");
            assert_eq!(store.next_epoch().expect("epoch"), 1);
            store.put_job(&rec).expect("put");
            let mut r2 = rec.clone();
            r2.state = JobState::Paused;
            store.put_job(&r2).expect("update");
        }
        let store = Store::open(dir.path()).expect("reopen");
        assert_eq!(store.next_epoch().expect("epoch"), 2);
        let jobs = store.jobs().expect("jobs");
        assert_eq!(jobs.len(), 1);
        assert_eq!(jobs[0].state, JobState::Paused);
        assert_eq!(jobs[0].settings, rec.settings);
        assert_eq!(jobs[0].requires, rec.requires);
        assert_eq!(jobs[0].notify, rec.notify);
        assert_eq!((&jobs[0].frames, jobs[0].order), (&rec.frames, rec.order));
    }

    /// The schema as the versions before migrations left it: made by `CREATE TABLE IF NOT
    /// EXISTS`, the sequence columns added by `ALTER TABLE`, `user_version` 0 (copied from the
    /// old `Store::open`).
    const PRE_MIGRATION_SCHEMA: &str = "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
         CREATE TABLE IF NOT EXISTS jobs (
             id INTEGER PRIMARY KEY,
             name TEXT NOT NULL,
             scene_id TEXT NOT NULL,
             priority INTEGER NOT NULL,
             settings TEXT NOT NULL,
             state TEXT NOT NULL,
             created_ms INTEGER NOT NULL,
             finished_ms INTEGER,
             error TEXT,
             run_ms INTEGER NOT NULL DEFAULT 0,
             requires TEXT NOT NULL DEFAULT '[]',
             notify TEXT
         );
         CREATE TABLE IF NOT EXISTS workers (
             id INTEGER PRIMARY KEY,
             name TEXT NOT NULL,
             threads INTEGER NOT NULL,
             registered_ms INTEGER NOT NULL
         );
         ALTER TABLE jobs ADD COLUMN frames TEXT; ALTER TABLE jobs ADD COLUMN frame_order TEXT NOT NULL DEFAULT 'frame';";

    fn user_version(dir: &Path) -> i64 {
        let conn = Connection::open(dir.join("pathfarm.db")).expect("db");
        conn.pragma_query_value(None, "user_version", |r| r.get(0)).expect("user_version")
    }

    #[test]
    fn a_pre_migration_database_opens_with_its_data() {
        let dir = tempfile::tempdir().expect("tempdir");
        {
            let conn = Connection::open(dir.path().join("pathfarm.db")).expect("db");
            conn.execute_batch(PRE_MIGRATION_SCHEMA).expect("old schema");
            conn.execute_batch(
                "INSERT INTO jobs (id, name, scene_id, priority, settings, state, created_ms, run_ms, requires, frames, frame_order)
                     VALUES (7, 'old job', 'scene-a', 3, '{\"width\":16,\"height\":8,\"spp\":4}', 'paused', 1234, 55,
                             '[\"gpu\"]', '1-3', 'frame');
                 INSERT INTO meta (key, value) VALUES ('epoch', 4), ('max_job_id', 9);",
            )
            .expect("old rows");
        }
        assert_eq!(user_version(dir.path()), 0);
        for reopen in 0..2 {
            let store = Store::open(dir.path()).expect("open");
            assert_eq!(user_version(dir.path()), SCHEMA_VERSION as i64, "reopen {reopen}");
            let jobs = store.jobs().expect("jobs");
            assert_eq!(jobs.len(), 1);
            let j = &jobs[0];
            assert_eq!((j.id, j.name.as_str(), j.scene_id.as_str(), j.priority), (7, "old job", "scene-a", 3));
            assert_eq!((j.state, j.created_ms, j.run_ms), (JobState::Paused, 1234, 55));
            assert_eq!(j.settings, RenderSettings::new(16, 8, 4));
            assert_eq!(j.requires, vec!["gpu".to_string()]);
            assert_eq!(j.frames.as_ref().map(|f| f.spec().to_string()).as_deref(), Some("1-3"));
            assert_eq!(store.max_job_id().expect("max id"), 9);
            assert_eq!(store.next_epoch().expect("epoch"), 5 + reopen);
        }
    }

    #[test]
    fn a_database_from_a_newer_version_is_refused_untouched() {
        let dir = tempfile::tempdir().expect("tempdir");
        drop(Store::open(dir.path()).expect("create"));
        let newer = SCHEMA_VERSION as i64 + 1;
        {
            let conn = Connection::open(dir.path().join("pathfarm.db")).expect("db");
            conn.execute_batch(&format!(
                "CREATE TABLE future (x INTEGER); INSERT INTO future VALUES (42); PRAGMA user_version = {newer};"
            ))
            .expect("newer schema");
        }
        let e = Store::open(dir.path()).err().expect("a newer database must be refused");
        let msg = format!("{e:#}");
        assert!(
            msg.contains(&format!("schema version {newer}, newer than this coordinator's {SCHEMA_VERSION}")),
            "{msg}"
        );
        assert_eq!(user_version(dir.path()), newer);
        let conn = Connection::open(dir.path().join("pathfarm.db")).expect("db");
        let x: i64 = conn.query_row("SELECT x FROM future", [], |r| r.get(0)).expect("future row");
        assert_eq!(x, 42);
    }

    #[test]
    fn databases_without_notify_are_migrated() {
        let dir = tempfile::tempdir().expect("tempdir");
        {
            let conn = Connection::open(dir.path().join("pathfarm.db")).expect("db");
            conn.execute_batch(
                "CREATE TABLE jobs (id INTEGER PRIMARY KEY, name TEXT NOT NULL, scene_id TEXT NOT NULL,
                     priority INTEGER NOT NULL, settings TEXT NOT NULL, state TEXT NOT NULL,
                     created_ms INTEGER NOT NULL, finished_ms INTEGER, error TEXT,
                     run_ms INTEGER NOT NULL DEFAULT 0, requires TEXT NOT NULL DEFAULT '[]');
                 INSERT INTO jobs (id, name, scene_id, priority, settings, state, created_ms)
                     VALUES (1, 'old', 's', 0, '{\"width\":8,\"height\":8,\"spp\":4}', 'queued', 0);",
            )
            .expect("old schema");
        }
        let store = Store::open(dir.path()).expect("open");
        let jobs = store.jobs().expect("jobs");
        assert_eq!(jobs.len(), 1);
        assert_eq!(jobs[0].notify, None);
    }

    #[test]
    fn damaged_job_rows_are_skipped() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::open(dir.path()).expect("open");
        let mut rec = JobRecord {
            id: 1,
            name: "good".into(),
            scene_id: "s".into(),
            priority: 0,
            settings: RenderSettings::new(8, 8, 4),
            requires: vec!["highmem".into()],
            notify: None,
            frames: None,
            order: FrameOrder::Frame,
            state: JobState::Queued,
            created_ms: 10,
            finished_ms: None,
            error: None,
            run_ms: 0,
        };
        store.put_job(&rec).expect("put");
        rec.id = 4;
        store.put_job(&rec).expect("put");
        store
            .conn
            .execute_batch(
                "INSERT INTO jobs (id, name, scene_id, priority, settings, state, created_ms)
                     VALUES (2, 'bad state', 's', 0, '{\"width\":8,\"height\":8,\"spp\":4}', 'exploded', 0);
                 INSERT INTO jobs (id, name, scene_id, priority, settings, state, created_ms)
                     VALUES (3, 'bad settings', 's', 0, 'not json', 'queued', 0);
                 INSERT INTO jobs (id, name, scene_id, priority, settings, state, created_ms)
                     VALUES (5, 'bad type', 's', 'high', '{}', 'queued', 0);",
            )
            .expect("bad rows");
        let ids: Vec<JobId> = store.jobs().expect("jobs").iter().map(|j| j.id).collect();
        assert_eq!(ids, vec![1, 4]);
        assert_eq!(store.max_job_id().expect("max id"), 5);
    }
}
