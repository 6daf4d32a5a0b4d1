-- Kept in step with ../0006_nodes.sql (comments there).
CREATE TABLE nodes (
    name          TEXT PRIMARY KEY,
    url           TEXT NOT NULL,
    version       TEXT NOT NULL,
    started_at    BIGINT NOT NULL,
    heartbeat_at  BIGINT NOT NULL,
    machines      TEXT NOT NULL DEFAULT '{}'
);
ALTER TABLE machines ADD COLUMN node TEXT;
ALTER TABLE pendants ADD COLUMN node TEXT;
CREATE TABLE cluster (
    id           BIGINT PRIMARY KEY CHECK (id = 1),
    node_secret  TEXT NOT NULL
);
CREATE TABLE program_chunks (
    sha256  TEXT NOT NULL,
    seq     BIGINT NOT NULL,
    data    BYTEA NOT NULL,
    PRIMARY KEY (sha256, seq)
);
ALTER TABLE events ADD COLUMN node TEXT;
