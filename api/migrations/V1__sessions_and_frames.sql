-- Sessions and their frames. IF NOT EXISTS: a database made before the
-- migrations ran through refinery has these already and is adopted as is.
CREATE TABLE IF NOT EXISTS sessions (
    id BIGSERIAL PRIMARY KEY,
    record JSONB NOT NULL
);
CREATE TABLE IF NOT EXISTS frames (
    session BIGINT NOT NULL REFERENCES sessions (id) ON DELETE CASCADE,
    idx BIGINT NOT NULL,
    meta JSONB NOT NULL,            -- pose (c2w), time, source, action, player
    latent BYTEA NOT NULL,          -- f32 little-endian; empty without a model
    png BYTEA NOT NULL,
    depth_png16 BYTEA NOT NULL,     -- empty when none was given
    PRIMARY KEY (session, idx)
);
