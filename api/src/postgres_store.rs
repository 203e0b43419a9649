//! The store on PostgreSQL (`--store postgres://…`): sessions and frames
//! in tables of their own, under a versioned schema that migrates itself
//! on connect. Every write is one committed transaction before it returns
//! (PostgreSQL's default `synchronous_commit = on` flushes the WAL first).

use std::sync::Mutex;
use std::time::Duration;

use postgres::{Client, NoTls};

use crate::records::{FrameMeta, FrameRecord, SessionRecord, StoreError, err};

/// Schema versions in order; version `i + 1` is `MIGRATIONS[i]`. Append, never edit.
const MIGRATIONS: &[&str] = &["
    CREATE TABLE sessions (
        id BIGSERIAL PRIMARY KEY,
        record JSONB NOT NULL
    );
    CREATE TABLE frames (
        session BIGINT NOT NULL REFERENCES sessions (id) ON DELETE CASCADE,
        idx BIGINT NOT NULL,
        meta JSONB NOT NULL,            -- pose (c2w), time, source, action, player
        latent BYTEA NOT NULL,          -- f32 little-endian; empty without a model
        png BYTEA NOT NULL,
        depth_png16 BYTEA NOT NULL,     -- empty when none was given
        PRIMARY KEY (session, idx)
    );", "
    -- When the session's newest frame was written: what retention reads.
    ALTER TABLE sessions ADD COLUMN written TIMESTAMPTZ NOT NULL DEFAULT now();"];

/// Connections per server: requests on different sessions (a step's commit,
/// another's catch-up) need not wait for one another's round trips.
const CONNECTIONS: usize = 4;

pub struct PgStore {
    url: String,
    clients: Vec<Mutex<Client>>,
    next: std::sync::atomic::AtomicUsize,
}

/// A query's error: `Unavailable` when the connection is gone, else `Failed`.
fn db(e: postgres::Error) -> StoreError {
    // SQLSTATE classes 08 (connection exception) and 57 (operator intervention: a shutdown).
    let dropped = e.code().is_some_and(|c| c.code().starts_with("08") || c.code().starts_with("57"));
    // No server error at all: the socket itself failed.
    if e.is_closed() || dropped || e.as_db_error().is_none() {
        StoreError::Unavailable(e.to_string())
    } else {
        err(e)
    }
}

/// A connection string fit to print or answer: the password replaced by
/// `***` (`postgres://user:***@host/db`, or `password=***` in the key=value form).
pub fn redacted(url: &str) -> String {
    if let Some((scheme, rest)) = url.split_once("://") {
        let (authority, tail) = rest.split_at(rest.find(['/', '?']).unwrap_or(rest.len()));
        if let Some((userinfo, host)) = authority.rsplit_once('@')
            && let Some((user, _password)) = userinfo.split_once(':')
        {
            return format!("{scheme}://{user}:***@{host}{tail}");
        }
        return url.to_string();
    }
    url.split_whitespace()
        .map(|kv| match kv.split_once('=') {
            Some((k, _)) if k.eq_ignore_ascii_case("password") => format!("{k}=***"),
            _ => kv.to_string(),
        })
        .collect::<Vec<_>>()
        .join(" ")
}

fn id(v: u64) -> Result<i64, StoreError> {
    i64::try_from(v).map_err(|_| err(format!("id {v} does not fit PostgreSQL's BIGINT")))
}

fn latent_bytes(latent: &[f32]) -> Vec<u8> {
    latent.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn frame_of(row: &postgres::Row) -> Result<FrameRecord, StoreError> {
    let meta: String = row.get(0);
    let latent: Vec<u8> = row.get(1);
    Ok(FrameRecord {
        meta: serde_json::from_str::<FrameMeta>(&meta).map_err(err)?,
        latent: latent.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect(),
        png: row.get(2),
        depth_png16: row.get(3),
    })
}

impl Drop for PgStore {
    /// A `postgres::Client` closes on a Tokio runtime of its own, which cannot
    /// start inside the server's: the clients are dropped on a plain thread.
    fn drop(&mut self) {
        let clients = std::mem::take(&mut self.clients);
        let _ = std::thread::spawn(move || drop(clients)).join();
    }
}

impl PgStore {
    /// Connects and brings the schema to the newest version.
    pub fn connect(url: &str) -> Result<PgStore, StoreError> {
        let mut client = Client::connect(url, NoTls).map_err(|e| StoreError::Unavailable(format!("{}: {e}", redacted(url))))?;
        let mut txn = client.transaction().map_err(db)?;
        txn.batch_execute("CREATE TABLE IF NOT EXISTS schema_version (version INT NOT NULL); LOCK TABLE schema_version;").map_err(db)?;
        let current: i32 = txn.query_one("SELECT coalesce(max(version), 0) FROM schema_version", &[]).map_err(db)?.get(0);
        if current as usize > MIGRATIONS.len() {
            return Err(err(format!("{}: schema version {current} is newer than this server's {}", redacted(url), MIGRATIONS.len())));
        }
        for (i, sql) in MIGRATIONS.iter().enumerate().skip(current as usize) {
            txn.batch_execute(sql).map_err(db)?;
            txn.execute("INSERT INTO schema_version (version) VALUES ($1)", &[&(i as i32 + 1)]).map_err(db)?;
        }
        txn.commit().map_err(db)?;
        let mut clients = vec![Mutex::new(client)];
        for _ in 1..CONNECTIONS {
            clients.push(Mutex::new(Client::connect(url, NoTls).map_err(|e| StoreError::Unavailable(format!("{}: {e}", redacted(url))))?));
        }
        Ok(PgStore { url: url.to_string(), clients, next: Default::default() })
    }

    /// A free connection (else the next in turn), opened again when it was
    /// lost (the database restarted): requests fail with `Unavailable` while
    /// it is down and succeed again once it is back.
    fn client(&self) -> Result<std::sync::MutexGuard<'_, Client>, StoreError> {
        let free = self.clients.iter().find_map(|c| c.try_lock().ok());
        let mut client = match free {
            Some(client) => client,
            None => {
                let turn = self.next.fetch_add(1, std::sync::atomic::Ordering::Relaxed) % self.clients.len();
                self.clients[turn].lock().unwrap_or_else(|poisoned| poisoned.into_inner())
            }
        };
        if client.is_closed() {
            *client = Client::connect(&self.url, NoTls).map_err(|e| StoreError::Unavailable(format!("{}: {e}", redacted(&self.url))))?;
        }
        Ok(client)
    }

    /// One round trip: whether the database answers now.
    pub fn ping(&self) -> Result<(), StoreError> {
        self.client()?.simple_query("SELECT 1").map(|_| ()).map_err(db)
    }

    pub fn create_session(&self, record: &SessionRecord, first: &FrameRecord) -> Result<u64, StoreError> {
        let mut client = self.client()?;
        let mut txn = client.transaction().map_err(db)?;
        let record = serde_json::to_string(record).map_err(err)?;
        let session: i64 = txn.query_one("INSERT INTO sessions (record) VALUES ($1::text::jsonb) RETURNING id", &[&record]).map_err(db)?.get(0);
        insert_frame(&mut txn, session, 0, first)?; // a new session: its frame 0 is free
        txn.commit().map_err(db)?;
        Ok(session as u64)
    }

    pub fn put_frame(&self, session: u64, index: u64, frame: &FrameRecord) -> Result<(), StoreError> {
        let mut client = self.client()?;
        let mut txn = client.transaction().map_err(db)?;
        if !insert_frame(&mut txn, id(session)?, id(index)?, frame)? {
            return Err(StoreError::Taken { session, index });
        }
        txn.execute("UPDATE sessions SET written = now() WHERE id = $1", &[&id(session)?]).map_err(db)?;
        txn.commit().map_err(db)
    }

    pub fn delete_session(&self, session: u64) -> Result<bool, StoreError> {
        Ok(self.client()?.execute("DELETE FROM sessions WHERE id = $1", &[&id(session)?]).map_err(db)? > 0)
    }

    pub fn idle_sessions(&self, idle: Duration) -> Result<Vec<u64>, StoreError> {
        let rows = self
            .client()?
            .query("SELECT id FROM sessions WHERE written <= now() - make_interval(secs => $1) ORDER BY written", &[&idle.as_secs_f64()])
            .map_err(db)?;
        Ok(rows.iter().map(|r| r.get::<_, i64>(0) as u64).collect())
    }

    pub fn delete_if_idle(&self, session: u64, idle: Duration) -> Result<bool, StoreError> {
        let sql = "DELETE FROM sessions WHERE id = $1 AND written <= now() - make_interval(secs => $2)";
        Ok(self.client()?.execute(sql, &[&id(session)?, &idle.as_secs_f64()]).map_err(db)? > 0)
    }

    pub fn sessions(&self) -> Result<Vec<(u64, SessionRecord)>, StoreError> {
        let rows = self.client()?.query("SELECT id, record::text FROM sessions ORDER BY id", &[]).map_err(db)?;
        rows.iter()
            .map(|r| {
                let (session, record): (i64, String) = (r.get(0), r.get(1));
                Ok((session as u64, serde_json::from_str(&record).map_err(err)?))
            })
            .collect()
    }

    pub fn session(&self, session: u64) -> Result<Option<SessionRecord>, StoreError> {
        let row = self.client()?.query_opt("SELECT record::text FROM sessions WHERE id = $1", &[&id(session)?]).map_err(db)?;
        row.map(|r| serde_json::from_str(&r.get::<_, String>(0)).map_err(err)).transpose()
    }

    pub fn frames_from(&self, session: u64, start: u64) -> Result<Vec<FrameRecord>, StoreError> {
        let rows = self
            .client()?
            .query(
                "SELECT meta::text, latent, png, depth_png16 FROM frames WHERE session = $1 AND idx >= $2 ORDER BY idx",
                &[&id(session)?, &id(start)?],
            )
            .map_err(db)?;
        rows.iter().map(frame_of).collect()
    }

    pub fn frame(&self, session: u64, index: u64) -> Result<Option<FrameRecord>, StoreError> {
        let row = self
            .client()?
            .query_opt("SELECT meta::text, latent, png, depth_png16 FROM frames WHERE session = $1 AND idx = $2", &[&id(session)?, &id(index)?])
            .map_err(db)?;
        row.as_ref().map(frame_of).transpose()
    }
}

/// Writes frame `index` of `session` unless it is stored already (then
/// false): the primary key makes the database hand each index out once, so
/// two replicas stepping one session cannot both write the same frame.
fn insert_frame(txn: &mut postgres::Transaction, session: i64, index: i64, f: &FrameRecord) -> Result<bool, StoreError> {
    let meta = serde_json::to_string(&f.meta).map_err(err)?;
    let written = txn
        .execute(
            "INSERT INTO frames (session, idx, meta, latent, png, depth_png16) VALUES ($1, $2, $3::text::jsonb, $4, $5, $6)
             ON CONFLICT (session, idx) DO NOTHING",
            &[&session, &index, &meta, &latent_bytes(&f.latent), &f.png, &f.depth_png16],
        )
        .map_err(db)?;
    Ok(written == 1)
}
