-- A fork's link to the session it was forked from, and how many of that
-- session's frames it shares (read from the parent's rows, never copied).
-- The reference has no cascade: a session with forks is not deleted.
ALTER TABLE sessions ADD COLUMN IF NOT EXISTS parent BIGINT REFERENCES sessions (id);
ALTER TABLE sessions ADD COLUMN IF NOT EXISTS fork_at BIGINT;
CREATE INDEX IF NOT EXISTS sessions_parent ON sessions (parent);
