//! The durable store: sessions and every frame. Two backends behind one
//! type: one embedded `redb` file (the default; each write its own
//! transaction committed with `Durability::Immediate`, fsync before `commit`
//! returns) or a PostgreSQL database (`postgres_store`; each write committed
//! before it returns). The server answers only after that, so an
//! acknowledged frame survives a crash.

use std::path::Path;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use redb::{Database, Durability, ReadableTable, TableDefinition};

pub use crate::records::{ForkOf, FrameMeta, FrameRecord, SessionRecord, StoreError};
use crate::records::err;

/// session id → session record (JSON).
const SESSIONS: TableDefinition<u64, &[u8]> = TableDefinition::new("sessions");
/// (session id, frame index) → frame record (see [`FrameRecord::encode`]).
const FRAMES: TableDefinition<(u64, u64), &[u8]> = TableDefinition::new("frames");
/// "next_session" → the next session id.
const COUNTERS: TableDefinition<&str, u64> = TableDefinition::new("counters");
/// session id → when its newest frame was written (ms since the Unix epoch): what retention reads.
const WRITTEN: TableDefinition<u64, u64> = TableDefinition::new("written");
/// (parent, fork) → the frames the fork shares: the parent link, read from the parent's side.
const FORKS: TableDefinition<(u64, u64), u64> = TableDefinition::new("forks");

fn unix_ms(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

/// The write time (as `unix_ms`) at or before which a session has been idle for `idle`.
fn idle_cutoff(idle: Duration) -> u64 {
    unix_ms(SystemTime::now()).saturating_sub(idle.as_millis() as u64)
}

/// Where sessions and frames live.
pub enum Store {
    Redb(RedbStore),
    Postgres(crate::postgres_store::PgStore),
}

/// The same call on whichever backend this store is.
macro_rules! each_backend {
    ($self:ident, $s:ident => $call:expr) => {
        match $self {
            Store::Redb($s) => $call,
            Store::Postgres($s) => $call,
        }
    };
}

impl Store {
    /// A `postgres://` (or `postgresql://`) URL connects to PostgreSQL and
    /// migrates its schema; any other path opens or creates a redb file.
    /// How the store is named in logs and answers: a PostgreSQL URL without its password.
    pub fn describe(path: &Path) -> String {
        let text = path.to_string_lossy();
        if text.starts_with("postgres://") || text.starts_with("postgresql://") {
            crate::postgres_store::redacted(&text)
        } else {
            path.display().to_string()
        }
    }

    pub fn open(path: &Path) -> Result<Store, StoreError> {
        let text = path.to_string_lossy();
        if text.starts_with("postgres://") || text.starts_with("postgresql://") {
            Ok(Store::Postgres(crate::postgres_store::PgStore::connect(&text)?))
        } else {
            Ok(Store::Redb(RedbStore::open(path)?))
        }
    }

    /// Whether the store answers now (a redb file always does once open).
    pub fn ping(&self) -> Result<(), StoreError> {
        match self {
            Store::Postgres(s) => s.ping(),
            Store::Redb(_) => Ok(()),
        }
    }

    /// Stores a new session with its first frame; returns its id.
    pub fn create_session(&self, record: &SessionRecord, first: &FrameRecord) -> Result<u64, StoreError> {
        each_backend!(self, s => s.create_session(record, first))
    }

    /// Stores a fork (`record.fork` says of which session, sharing how many
    /// frames; nothing of the parent's is copied); returns its id, or
    /// [`StoreError::Missing`] when the parent is not stored.
    pub fn create_fork(&self, record: &SessionRecord) -> Result<u64, StoreError> {
        let Some(fork) = record.fork else { return Err(err("a fork's record names the session it was forked from")) };
        each_backend!(self, s => s.create_fork(record, fork))
    }

    /// Stores frame `index`, once: an index stored before is [`StoreError::Taken`].
    pub fn put_frame(&self, session: u64, index: u64, frame: &FrameRecord) -> Result<(), StoreError> {
        each_backend!(self, s => s.put_frame(session, index, frame))
    }

    /// Whether other servers may write this store too (PostgreSQL): a
    /// server then reads a session's new frames before each request on it.
    pub fn shared(&self) -> bool {
        matches!(self, Store::Postgres(_))
    }

    /// One session's record; `None` when there is none (never made, or deleted).
    pub fn session(&self, id: u64) -> Result<Option<SessionRecord>, StoreError> {
        each_backend!(self, s => s.session(id))
    }

    /// The frames stored under `session` itself from index `start` on, in
    /// index order (a fork's shared frames are stored under its parent).
    pub fn frames_from(&self, session: u64, start: u64) -> Result<Vec<FrameRecord>, StoreError> {
        each_backend!(self, s => s.frames_between(session, start, u64::MAX))
    }

    /// Removes a session and its frames; false when there was none;
    /// [`StoreError::HasForks`] while forks of it are stored.
    pub fn delete_session(&self, id: u64) -> Result<bool, StoreError> {
        each_backend!(self, s => s.delete_session(id))
    }

    pub fn sessions(&self) -> Result<Vec<(u64, SessionRecord)>, StoreError> {
        each_backend!(self, s => s.sessions())
    }

    /// Sessions with no frame written for `idle` or longer (retention's candidates).
    pub fn idle_sessions(&self, idle: Duration) -> Result<Vec<u64>, StoreError> {
        each_backend!(self, s => s.idle_sessions(idle))
    }

    /// Removes a session and its frames if no frame was written to it for
    /// `idle` (one written since it was listed keeps it); says whether it did.
    pub fn delete_if_idle(&self, id: u64, idle: Duration) -> Result<bool, StoreError> {
        each_backend!(self, s => s.delete_if_idle(id, idle))
    }

    /// Frames `0..end` of a session as it reads them, in index order: a
    /// fork's first frames from the sessions it was forked from.
    pub fn frames_before(&self, session: u64, end: u64) -> Result<Vec<FrameRecord>, StoreError> {
        let mut out = Vec::new();
        for (owner, start, end) in self.lineage(session, end)? {
            out.extend(each_backend!(self, s => s.frames_between(owner, start, end))?);
        }
        Ok(out)
    }

    /// Every frame of a session as it reads them, in index order.
    pub fn frames(&self, session: u64) -> Result<Vec<FrameRecord>, StoreError> {
        self.frames_before(session, u64::MAX)
    }

    /// Frame `index` of a session as it reads it (a fork's shared frames are its parent's).
    pub fn frame(&self, session: u64, index: u64) -> Result<Option<FrameRecord>, StoreError> {
        match self.lineage(session, index.saturating_add(1))?.last() {
            Some(&(owner, start, _)) if start <= index => each_backend!(self, s => s.frame(owner, index)),
            _ => Ok(None),
        }
    }

    /// Where frames `0..end` of `session` are stored: (session, start, end)
    /// runs, oldest first, following fork links to the first session.
    fn lineage(&self, session: u64, end: u64) -> Result<Vec<(u64, u64, u64)>, StoreError> {
        let (mut at, mut end, mut runs) = (session, end, Vec::new());
        loop {
            let record = self.session(at)?.ok_or(StoreError::Missing(at))?;
            let start = record.fork.map_or(0, |f| f.frames);
            if end > start {
                runs.push((at, start, end));
            }
            match record.fork {
                Some(f) => (at, end) = (f.parent, end.min(f.frames)),
                None => break,
            }
        }
        runs.reverse();
        Ok(runs)
    }
}

/// The embedded backend: one redb file.
pub struct RedbStore {
    db: Database,
}

impl RedbStore {
    pub fn open(path: &Path) -> Result<RedbStore, StoreError> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| err(format!("cannot create {}: {e}", dir.display())))?;
        }
        let db = Database::create(path).map_err(|e| err(format!("{}: {e}", path.display())))?;
        let txn = db.begin_write().map_err(err)?;
        txn.open_table(SESSIONS).map_err(err)?;
        txn.open_table(FRAMES).map_err(err)?;
        txn.open_table(COUNTERS).map_err(err)?;
        txn.open_table(FORKS).map_err(err)?;
        {
            // Stores written before retention existed: their sessions count as written now.
            let sessions = txn.open_table(SESSIONS).map_err(err)?;
            let mut written = txn.open_table(WRITTEN).map_err(err)?;
            let now = unix_ms(SystemTime::now());
            for row in sessions.iter().map_err(err)? {
                let id = row.map_err(err)?.0.value();
                if written.get(id).map_err(err)?.is_none() {
                    written.insert(id, now).map_err(err)?;
                }
            }
        }
        txn.commit().map_err(err)?;
        Ok(RedbStore { db })
    }

    fn write<T>(&self, f: impl FnOnce(&redb::WriteTransaction) -> Result<T, StoreError>) -> Result<T, StoreError> {
        let mut txn = self.db.begin_write().map_err(err)?;
        txn.set_durability(Durability::Immediate);
        let out = f(&txn)?;
        txn.commit().map_err(err)?;
        Ok(out)
    }

    /// Stores a new session with its first frame; returns its id.
    pub fn create_session(&self, record: &SessionRecord, first: &FrameRecord) -> Result<u64, StoreError> {
        self.write(|txn| {
            let mut counters = txn.open_table(COUNTERS).map_err(err)?;
            let id = counters.get("next_session").map_err(err)?.map_or(1, |v| v.value());
            counters.insert("next_session", id + 1).map_err(err)?;
            txn.open_table(SESSIONS).map_err(err)?.insert(id, serde_json::to_vec(record).map_err(err)?.as_slice()).map_err(err)?;
            txn.open_table(FRAMES).map_err(err)?.insert((id, 0), first.encode().as_slice()).map_err(err)?;
            txn.open_table(WRITTEN).map_err(err)?.insert(id, unix_ms(SystemTime::now())).map_err(err)?;
            Ok(id)
        })
    }

    pub fn create_fork(&self, record: &SessionRecord, fork: ForkOf) -> Result<u64, StoreError> {
        self.write(|txn| {
            if txn.open_table(SESSIONS).map_err(err)?.get(fork.parent).map_err(err)?.is_none() {
                return Err(StoreError::Missing(fork.parent));
            }
            let mut counters = txn.open_table(COUNTERS).map_err(err)?;
            let id = counters.get("next_session").map_err(err)?.map_or(1, |v| v.value());
            counters.insert("next_session", id + 1).map_err(err)?;
            txn.open_table(SESSIONS).map_err(err)?.insert(id, serde_json::to_vec(record).map_err(err)?.as_slice()).map_err(err)?;
            txn.open_table(FORKS).map_err(err)?.insert((fork.parent, id), fork.frames).map_err(err)?;
            txn.open_table(WRITTEN).map_err(err)?.insert(id, unix_ms(SystemTime::now())).map_err(err)?;
            Ok(id)
        })
    }

    pub fn put_frame(&self, session: u64, index: u64, frame: &FrameRecord) -> Result<(), StoreError> {
        self.write(|txn| {
            let mut frames = txn.open_table(FRAMES).map_err(err)?;
            if frames.get((session, index)).map_err(err)?.is_some() {
                return Err(StoreError::Taken { session, index });
            }
            frames.insert((session, index), frame.encode().as_slice()).map_err(err)?;
            txn.open_table(WRITTEN).map_err(err)?.insert(session, unix_ms(SystemTime::now())).map_err(err)?;
            Ok(())
        })
    }

    pub fn session(&self, id: u64) -> Result<Option<SessionRecord>, StoreError> {
        let txn = self.db.begin_read().map_err(err)?;
        let table = txn.open_table(SESSIONS).map_err(err)?;
        table.get(id).map_err(err)?.map(|v| serde_json::from_slice(v.value()).map_err(err)).transpose()
    }

    /// Removes a session and its frames; false when there was none.
    pub fn delete_session(&self, id: u64) -> Result<bool, StoreError> {
        self.write(|txn| remove_session(txn, id))
    }

    /// Idle sessions without forks (a session with forks outlives them).
    pub fn idle_sessions(&self, idle: Duration) -> Result<Vec<u64>, StoreError> {
        let cutoff = idle_cutoff(idle);
        let txn = self.db.begin_read().map_err(err)?;
        let forks = txn.open_table(FORKS).map_err(err)?;
        let mut out = Vec::new();
        for row in txn.open_table(WRITTEN).map_err(err)?.iter().map_err(err)? {
            let (id, written) = row.map_err(err)?;
            if written.value() <= cutoff && forks_of(&forks, id.value())?.is_empty() {
                out.push(id.value());
            }
        }
        Ok(out)
    }

    pub fn delete_if_idle(&self, id: u64, idle: Duration) -> Result<bool, StoreError> {
        let cutoff = idle_cutoff(idle);
        self.write(|txn| {
            let written = txn.open_table(WRITTEN).map_err(err)?.get(id).map_err(err)?.map(|v| v.value());
            if written.is_none_or(|w| w > cutoff) || !forks_of(&txn.open_table(FORKS).map_err(err)?, id)?.is_empty() {
                return Ok(false);
            }
            remove_session(txn, id)
        })
    }

    pub fn sessions(&self) -> Result<Vec<(u64, SessionRecord)>, StoreError> {
        let txn = self.db.begin_read().map_err(err)?;
        let table = txn.open_table(SESSIONS).map_err(err)?;
        let mut out = Vec::new();
        for row in table.iter().map_err(err)? {
            let (k, v) = row.map_err(err)?;
            out.push((k.value(), serde_json::from_slice(v.value()).map_err(err)?));
        }
        Ok(out)
    }

    /// Frames `start..end` stored under `session` itself, in index order.
    pub fn frames_between(&self, session: u64, start: u64, end: u64) -> Result<Vec<FrameRecord>, StoreError> {
        let txn = self.db.begin_read().map_err(err)?;
        let table = txn.open_table(FRAMES).map_err(err)?;
        let mut out = Vec::new();
        if end <= start {
            return Ok(out);
        }
        for row in table.range((session, start)..(session, end)).map_err(err)? {
            let (_, v) = row.map_err(err)?;
            out.push(FrameRecord::decode(v.value())?);
        }
        Ok(out)
    }

    pub fn frame(&self, session: u64, index: u64) -> Result<Option<FrameRecord>, StoreError> {
        let txn = self.db.begin_read().map_err(err)?;
        let table = txn.open_table(FRAMES).map_err(err)?;
        table.get((session, index)).map_err(err)?.map(|v| FrameRecord::decode(v.value())).transpose()
    }
}

/// The forks of `session` stored in `forks`.
fn forks_of(forks: &impl ReadableTable<(u64, u64), u64>, session: u64) -> Result<Vec<u64>, StoreError> {
    let mut out = Vec::new();
    for row in forks.range((session, 0)..=(session, u64::MAX)).map_err(err)? {
        out.push(row.map_err(err)?.0.value().1);
    }
    Ok(out)
}

/// Removes a session, its frames, its write time and its link to the session
/// it was forked from in `txn`; false when there was none; refused while it has forks.
fn remove_session(txn: &redb::WriteTransaction, id: u64) -> Result<bool, StoreError> {
    let mut forks = txn.open_table(FORKS).map_err(err)?;
    let children = forks_of(&forks, id)?;
    if !children.is_empty() {
        return Err(StoreError::HasForks { session: id, forks: children });
    }
    let Some(record) = txn.open_table(SESSIONS).map_err(err)?.remove(id).map_err(err)?.map(|v| v.value().to_vec()) else {
        return Ok(false);
    };
    if let Some(fork) = serde_json::from_slice::<SessionRecord>(&record).map_err(err)?.fork {
        forks.remove((fork.parent, id)).map_err(err)?;
    }
    txn.open_table(FRAMES).map_err(err)?.retain_in((id, 0)..=(id, u64::MAX), |_, _| false).map_err(err)?;
    txn.open_table(WRITTEN).map_err(err)?.remove(id).map_err(err)?;
    Ok(true)
}
