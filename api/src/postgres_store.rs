//! The store on PostgreSQL (`--store postgres://…`): sessions and frames
//! in tables of their own. Connections come from an r2d2 pool, checked as
//! they are taken and opened again after the database restarted; the schema
//! migrates on connect through refinery (`api/migrations`); the link is TLS
//! when the URL asks for it (`postgres_tls`). Every write is one committed
//! transaction before it returns (PostgreSQL's default `synchronous_commit =
//! on` flushes the WAL first).

use std::time::Duration;

use r2d2::{Pool, PooledConnection};
use r2d2_postgres::PostgresConnectionManager;
use tokio_postgres_rustls::MakeRustlsConnect;

use crate::postgres_tls;
use crate::records::{ForkOf, FrameMeta, FrameRecord, SessionRecord, StoreError, err};

mod embedded {
    refinery::embed_migrations!("migrations");
}

/// Connections per server: requests on different sessions (a step's commit,
/// another's catch-up) need not wait for one another's round trips.
const CONNECTIONS: u32 = 4;

/// How long a request waits for a connection before it answers that the
/// store is unavailable (the database down, or every connection busy).
const CHECKOUT: Duration = Duration::from_secs(2);

/// Held while migrating, so replicas that start together migrate one at a time.
const MIGRATION_LOCK: i64 = 0x776f_726c_6470_6163; // "worldpac"

/// r2d2_postgres's manager with errors that say what happened: the driver's
/// own text is its kind alone ("db error"), the server's message is in its
/// source, and the pool reports an error by its text.
struct Explaining(PostgresConnectionManager<MakeRustlsConnect>);

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct Explained(String);

/// An error and its sources, one after another.
fn explained(e: &(dyn std::error::Error + 'static)) -> String {
    std::iter::successors(Some(e), |e| e.source()).map(ToString::to_string).collect::<Vec<_>>().join(": ")
}

impl r2d2::ManageConnection for Explaining {
    type Connection = postgres::Client;
    type Error = Explained;

    fn connect(&self) -> Result<postgres::Client, Explained> {
        self.0.connect().map_err(|e| Explained(explained(&e)))
    }
    fn is_valid(&self, client: &mut postgres::Client) -> Result<(), Explained> {
        self.0.is_valid(client).map_err(|e| Explained(explained(&e)))
    }
    fn has_broken(&self, client: &mut postgres::Client) -> bool {
        self.0.has_broken(client)
    }
}

pub struct PgStore {
    /// The URL fit to print (`redacted`): what errors name.
    shown: String,
    /// Some until drop (see `Drop`).
    pool: Option<Pool<Explaining>>,
}

/// A query's error: `Unavailable` when the connection is gone, else `Failed`.
fn db(e: postgres::Error) -> StoreError {
    // SQLSTATE classes 08 (connection exception) and 57 (operator intervention: a shutdown).
    let dropped = e.code().is_some_and(|c| c.code().starts_with("08") || c.code().starts_with("57"));
    // No server error at all: the socket itself failed.
    if e.is_closed() || dropped || e.as_db_error().is_none() {
        StoreError::Unavailable(explained(&e))
    } else {
        err(explained(&e))
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

/// A session's row (`id, record::text, parent, fork_at`) as its record: the
/// fork link lives in columns, where the database keeps it referring to a stored session.
fn session_of(row: &postgres::Row) -> Result<(u64, SessionRecord), StoreError> {
    let (session, record, parent, fork_at): (i64, String, Option<i64>, Option<i64>) = (row.get(0), row.get(1), row.get(2), row.get(3));
    let mut record: SessionRecord = serde_json::from_str(&record).map_err(err)?;
    record.fork = parent.zip(fork_at).map(|(parent, frames)| ForkOf { parent: parent as u64, frames: frames as u64 });
    Ok((session as u64, record))
}

/// The record as stored in `record`: without the fork link, which has its columns.
fn record_json(record: &SessionRecord) -> Result<String, StoreError> {
    serde_json::to_string(&SessionRecord { fork: None, ..record.clone() }).map_err(err)
}

/// PostgreSQL's foreign_key_violation.
fn foreign_key_violation(e: &postgres::Error) -> bool {
    e.code() == Some(&postgres::error::SqlState::FOREIGN_KEY_VIOLATION)
}

const SESSION_COLUMNS: &str = "id, record::text, parent, fork_at";

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
    /// start inside the server's: the pool is dropped on a plain thread.
    fn drop(&mut self) {
        let pool = self.pool.take();
        let _ = std::thread::spawn(move || drop(pool)).join();
    }
}

impl PgStore {
    /// Connects (TLS as the URL says), fills the pool and brings the schema to
    /// the newest version.
    pub fn connect(url: &str) -> Result<PgStore, StoreError> {
        let shown = redacted(url);
        let link = postgres_tls::link(url).map_err(|e| err(format!("{shown}: {e}")))?;
        let pool = Pool::builder()
            .max_size(CONNECTIONS)
            .connection_timeout(CHECKOUT)
            .build(Explaining(PostgresConnectionManager::new(link.config, link.tls)))
            .map_err(|e| StoreError::Unavailable(format!("{shown}: {e}")))?;
        let store = PgStore { shown, pool: Some(pool) };
        store.migrate()?;
        Ok(store)
    }

    fn migrate(&self) -> Result<(), StoreError> {
        let mut client = self.client()?;
        client.batch_execute(&format!("SELECT pg_advisory_lock({MIGRATION_LOCK})")).map_err(db)?;
        let migrated = embedded::migrations::runner().run(&mut *client);
        client.batch_execute(&format!("SELECT pg_advisory_unlock({MIGRATION_LOCK})")).map_err(db)?;
        migrated.map(drop).map_err(|e| err(format!("{}: migrating the schema: {e}", self.shown)))
    }

    /// A pooled connection, or `Unavailable` after [`CHECKOUT`] (while the
    /// database is down: the pool opens new ones once it is back).
    fn client(&self) -> Result<PooledConnection<Explaining>, StoreError> {
        let pool = self.pool.as_ref().expect("the pool lives until the store is dropped");
        pool.get().map_err(|e| StoreError::Unavailable(format!("{}: {e}", self.shown)))
    }

    /// One round trip: whether the database answers now.
    pub fn ping(&self) -> Result<(), StoreError> {
        self.client()?.simple_query("SELECT 1").map(|_| ()).map_err(db)
    }

    pub fn create_session(&self, record: &SessionRecord, first: &FrameRecord) -> Result<u64, StoreError> {
        let mut client = self.client()?;
        let mut txn = client.transaction().map_err(db)?;
        let record = record_json(record)?;
        let session: i64 = txn.query_one("INSERT INTO sessions (record) VALUES ($1::text::jsonb) RETURNING id", &[&record]).map_err(db)?.get(0);
        insert_frame(&mut txn, session, 0, first)?; // a new session: its frame 0 is free
        txn.commit().map_err(db)?;
        Ok(session as u64)
    }

    /// One row: the parent's frames stay where they are. The reference makes
    /// the database refuse a parent deleted meanwhile.
    pub fn create_fork(&self, record: &SessionRecord, fork: ForkOf) -> Result<u64, StoreError> {
        let sql = "INSERT INTO sessions (record, parent, fork_at) VALUES ($1::text::jsonb, $2, $3) RETURNING id";
        match self.client()?.query_one(sql, &[&record_json(record)?, &id(fork.parent)?, &id(fork.frames)?]) {
            Ok(row) => Ok(row.get::<_, i64>(0) as u64),
            Err(e) if foreign_key_violation(&e) => Err(StoreError::Missing(fork.parent)),
            Err(e) => Err(db(e)),
        }
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

    /// Refused while forks of it are stored: the row is locked first, so a
    /// fork being made at the same time either commits before (and is named) or waits and then fails.
    pub fn delete_session(&self, session: u64) -> Result<bool, StoreError> {
        let mut client = self.client()?;
        let mut txn = client.transaction().map_err(db)?;
        if txn.query_opt("SELECT 1 FROM sessions WHERE id = $1 FOR UPDATE", &[&id(session)?]).map_err(db)?.is_none() {
            return Ok(false);
        }
        let forks: Vec<u64> = txn.query("SELECT id FROM sessions WHERE parent = $1 ORDER BY id", &[&id(session)?]).map_err(db)?.iter().map(|r| r.get::<_, i64>(0) as u64).collect();
        if !forks.is_empty() {
            return Err(StoreError::HasForks { session, forks });
        }
        txn.execute("DELETE FROM sessions WHERE id = $1", &[&id(session)?]).map_err(db)?;
        txn.commit().map_err(db)?;
        Ok(true)
    }

    /// Idle sessions without forks (a session with forks outlives them).
    pub fn idle_sessions(&self, idle: Duration) -> Result<Vec<u64>, StoreError> {
        let sql = "SELECT id FROM sessions s WHERE written <= now() - make_interval(secs => $1)
                   AND NOT EXISTS (SELECT 1 FROM sessions c WHERE c.parent = s.id) ORDER BY written";
        let rows = self.client()?.query(sql, &[&idle.as_secs_f64()]).map_err(db)?;
        Ok(rows.iter().map(|r| r.get::<_, i64>(0) as u64).collect())
    }

    pub fn delete_if_idle(&self, session: u64, idle: Duration) -> Result<bool, StoreError> {
        let sql = "DELETE FROM sessions s WHERE id = $1 AND written <= now() - make_interval(secs => $2)
                   AND NOT EXISTS (SELECT 1 FROM sessions c WHERE c.parent = s.id)";
        match self.client()?.execute(sql, &[&id(session)?, &idle.as_secs_f64()]) {
            Ok(n) => Ok(n > 0),
            Err(e) if foreign_key_violation(&e) => Ok(false), // forked meanwhile: kept
            Err(e) => Err(db(e)),
        }
    }

    pub fn sessions(&self) -> Result<Vec<(u64, SessionRecord)>, StoreError> {
        let rows = self.client()?.query(&format!("SELECT {SESSION_COLUMNS} FROM sessions ORDER BY id"), &[]).map_err(db)?;
        rows.iter().map(session_of).collect()
    }

    pub fn session(&self, session: u64) -> Result<Option<SessionRecord>, StoreError> {
        let row = self.client()?.query_opt(&format!("SELECT {SESSION_COLUMNS} FROM sessions WHERE id = $1"), &[&id(session)?]).map_err(db)?;
        Ok(row.as_ref().map(session_of).transpose()?.map(|(_, record)| record))
    }

    /// Frames `start..end` stored under `session` itself, in index order.
    pub fn frames_between(&self, session: u64, start: u64, end: u64) -> Result<Vec<FrameRecord>, StoreError> {
        let rows = self
            .client()?
            .query(
                "SELECT meta::text, latent, png, depth_png16 FROM frames WHERE session = $1 AND idx >= $2 AND idx < $3 ORDER BY idx",
                &[&id(session)?, &id(start)?, &id(end.min(i64::MAX as u64))?],
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
