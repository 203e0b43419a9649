-- When the session's newest frame was written: what retention reads.
ALTER TABLE sessions ADD COLUMN IF NOT EXISTS written TIMESTAMPTZ NOT NULL DEFAULT now();
