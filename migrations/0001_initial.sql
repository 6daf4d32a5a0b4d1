-- Fresa store, version 1. Times are Unix milliseconds (UTC).

CREATE TABLE machines (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT NOT NULL UNIQUE,
    backend     TEXT NOT NULL,
    config      TEXT NOT NULL DEFAULT '{}',   -- JSON handed to the backend plugin
    max_jog_mm  REAL NOT NULL DEFAULT 50.0,   -- per-request jog bound
    max_feed_mm_min REAL NOT NULL DEFAULT 5000.0,
    active_offset TEXT NOT NULL DEFAULT 'G54',
    created_at  INTEGER NOT NULL
);

-- Handwheel pendants (the pendant transport issue fills the behaviour).
CREATE TABLE pendants (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT NOT NULL UNIQUE,
    address     TEXT NOT NULL,
    dialect     TEXT NOT NULL DEFAULT 'firmware',
    machine_id  INTEGER REFERENCES machines(id) ON DELETE SET NULL,
    config      TEXT NOT NULL DEFAULT '{}',
    created_at  INTEGER NOT NULL
);

-- A program is stored once on disk under the data dir, named by its sha256.
CREATE TABLE jobs (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT NOT NULL,
    machine_id  INTEGER NOT NULL REFERENCES machines(id),
    sha256      TEXT NOT NULL,
    size_bytes  INTEGER NOT NULL,
    line_count  INTEGER NOT NULL,
    analysis    TEXT,                          -- JSON: bounds, length, ETA, warnings
    source      TEXT NOT NULL DEFAULT 'http',  -- http | pendant:<id> | cli
    created_at  INTEGER NOT NULL
);
CREATE INDEX jobs_machine ON jobs(machine_id);

-- One execution attempt of a job. Resume continues the same run from last_line + 1.
CREATE TABLE job_runs (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id      INTEGER NOT NULL REFERENCES jobs(id),
    machine_id  INTEGER NOT NULL REFERENCES machines(id),
    state       TEXT NOT NULL CHECK (state IN
                 ('queued','running','paused','completed','failed','cancelled','interrupted')),
    last_line   INTEGER NOT NULL DEFAULT 0,    -- last acknowledged source line (0 = none)
    message     TEXT,
    created_at  INTEGER NOT NULL,
    started_at  INTEGER,
    ended_at    INTEGER,
    updated_at  INTEGER NOT NULL
);
CREATE INDEX job_runs_job ON job_runs(job_id);
CREATE INDEX job_runs_state ON job_runs(state);

CREATE TABLE work_offsets (
    machine_id  INTEGER NOT NULL REFERENCES machines(id) ON DELETE CASCADE,
    name        TEXT NOT NULL CHECK (name IN ('G54','G55','G56','G57','G58','G59')),
    x REAL NOT NULL DEFAULT 0, y REAL NOT NULL DEFAULT 0,
    z REAL NOT NULL DEFAULT 0, a REAL NOT NULL DEFAULT 0,
    updated_at  INTEGER NOT NULL,
    PRIMARY KEY (machine_id, name)
);

-- Append-only history of part zeros: where, who, when, from what.
CREATE TABLE part_zeros (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    machine_id  INTEGER NOT NULL REFERENCES machines(id) ON DELETE CASCADE,
    x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL, a REAL NOT NULL,
    source      TEXT NOT NULL,                 -- api | pendant:<id> | robot | ...
    actor       TEXT NOT NULL,                 -- token name or 'local'
    note        TEXT,
    created_at  INTEGER NOT NULL
);

CREATE TABLE tokens (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT NOT NULL,
    role        TEXT NOT NULL CHECK (role IN ('viewer','operator','admin')),
    hash        TEXT NOT NULL UNIQUE,          -- sha256 of the secret; the secret is never stored
    created_at  INTEGER NOT NULL
);

-- Append-only event and audit log; ids are the SSE event ids.
CREATE TABLE events (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    type        TEXT NOT NULL,
    machine_id  INTEGER,
    actor       TEXT,
    data        TEXT NOT NULL,
    created_at  INTEGER NOT NULL
);
CREATE INDEX events_machine ON events(machine_id, id);
