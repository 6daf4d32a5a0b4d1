-- Generated: see server/core/src/store/baseline.rs. Do not edit.

CREATE TABLE machines (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT NOT NULL UNIQUE,
    backend     TEXT NOT NULL,
    config      TEXT NOT NULL DEFAULT '{}',   -- JSON handed to the backend plugin
    max_jog_mm  REAL NOT NULL DEFAULT 50.0,   -- per-request jog bound
    max_feed_mm_min REAL NOT NULL DEFAULT 5000.0,
    active_offset TEXT NOT NULL DEFAULT 'G54',
    created_at  INTEGER NOT NULL
, node TEXT, max_probe_feed_mm_min REAL NOT NULL DEFAULT 300.0, feed_override_min REAL NOT NULL DEFAULT 10.0, feed_override_max REAL NOT NULL DEFAULT 200.0, spindle_override_min REAL NOT NULL DEFAULT 50.0, spindle_override_max REAL NOT NULL DEFAULT 150.0, rapid_override_min REAL NOT NULL DEFAULT 25.0, safe_z_mm REAL, maintenance TEXT NOT NULL DEFAULT '[]');

CREATE TABLE pendants (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT NOT NULL UNIQUE,
    address     TEXT NOT NULL,
    dialect     TEXT NOT NULL DEFAULT 'firmware',
    machine_id  INTEGER REFERENCES machines(id) ON DELETE SET NULL,
    config      TEXT NOT NULL DEFAULT '{}',
    created_at  INTEGER NOT NULL
, node TEXT);

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
, part_zero TEXT, unstored_line INTEGER, from_line INTEGER, height_map_id INTEGER);

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
, expires_at INTEGER, last_used_at INTEGER);

CREATE TABLE events (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    type        TEXT NOT NULL,
    machine_id  INTEGER,
    actor       TEXT,
    data        TEXT NOT NULL,
    created_at  INTEGER NOT NULL
, node TEXT);

CREATE INDEX events_machine ON events(machine_id, id);

CREATE TABLE pendant_macros (
    pendant_id  INTEGER NOT NULL REFERENCES pendants(id) ON DELETE CASCADE,
    slot        INTEGER NOT NULL CHECK (slot BETWEEN 1 AND 4),
    action      TEXT NOT NULL,
    updated_at  INTEGER NOT NULL,
    PRIMARY KEY (pendant_id, slot)
);

CREATE UNIQUE INDEX tokens_name ON tokens(name);

CREATE INDEX events_created ON events(created_at);

CREATE TABLE event_retention (
    id              INTEGER PRIMARY KEY CHECK (id = 1),
    pruned_through  INTEGER NOT NULL
);

CREATE TABLE webhooks (
    id               INTEGER PRIMARY KEY,
    url              TEXT NOT NULL,
    -- JSON array of event types; `job` matches `job.*`; empty: every persisted event.
    events           TEXT NOT NULL DEFAULT '[]',
    -- The HMAC-SHA256 key. Kept in the clear because signing needs it; shown once at creation
    -- and never by the API again.
    secret           TEXT NOT NULL,
    created_by       TEXT NOT NULL,
    created_at       INTEGER NOT NULL,
    -- The last delivery: HTTP status (NULL: no answer), error, attempts it took, when it ended.
    last_status      INTEGER,
    last_error       TEXT,
    last_attempts    INTEGER NOT NULL DEFAULT 0,
    last_delivery_at INTEGER,
    delivered        INTEGER NOT NULL DEFAULT 0,
    failed           INTEGER NOT NULL DEFAULT 0
);

CREATE TABLE nodes (
    name          TEXT PRIMARY KEY,
    -- Where other nodes reach it (forwarded requests), e.g. http://hall2.lan:7878.
    url           TEXT NOT NULL,
    version       TEXT NOT NULL,
    started_at    INTEGER NOT NULL,
    heartbeat_at  INTEGER NOT NULL,
    -- JSON object: machine id -> that machine's last status, written with each heartbeat, so
    -- the other nodes list remote machines without asking.
    machines      TEXT NOT NULL DEFAULT '{}'
);

CREATE TABLE cluster (
    id           INTEGER PRIMARY KEY CHECK (id = 1),
    node_secret  TEXT NOT NULL
);

CREATE TABLE program_chunks (
    sha256  TEXT NOT NULL,
    seq     INTEGER NOT NULL,
    data    BLOB NOT NULL,
    PRIMARY KEY (sha256, seq)
);

CREATE TABLE machine_tools (
    machine_id  INTEGER NOT NULL REFERENCES machines(id) ON DELETE CASCADE,
    tool        INTEGER NOT NULL CHECK (tool >= 0),
    diameter_mm REAL NOT NULL,
    length_mm   REAL NOT NULL DEFAULT 0,
    description TEXT NOT NULL DEFAULT '',
    updated_at  INTEGER NOT NULL,
    PRIMARY KEY (machine_id, tool)
);

CREATE TABLE store_probe (
    id    INTEGER PRIMARY KEY CHECK (id = 1),
    at_ms INTEGER NOT NULL
);

CREATE TABLE machine_run_settings (
    machine_id         INTEGER PRIMARY KEY REFERENCES machines(id) ON DELETE CASCADE,
    settings           TEXT NOT NULL,
    setter_reference_z REAL,
    updated_at         INTEGER NOT NULL
);

CREATE TABLE height_maps (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    machine_id  INTEGER NOT NULL REFERENCES machines(id) ON DELETE CASCADE,
    state       TEXT NOT NULL CHECK (state IN ('probing','complete','stopped','failed')),
    x0          REAL NOT NULL,
    x1          REAL NOT NULL,
    y0          REAL NOT NULL,
    y1          REAL NOT NULL,
    nx          INTEGER NOT NULL,
    ny          INTEGER NOT NULL,
    clearance   REAL NOT NULL,
    distance    REAL NOT NULL,
    feed        REAL NOT NULL,
    offset_x    REAL NOT NULL,
    offset_y    REAL NOT NULL,
    offset_z    REAL NOT NULL,
    points      TEXT NOT NULL,
    message     TEXT,
    created_by  TEXT NOT NULL,
    created_at  INTEGER NOT NULL,
    finished_at INTEGER
);

CREATE INDEX height_maps_machine ON height_maps(machine_id, id);

CREATE TABLE queue_entries (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    machine_id      INTEGER NOT NULL REFERENCES machines(id) ON DELETE CASCADE,
    job_id          INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    position        INTEGER NOT NULL,
    count           INTEGER NOT NULL,
    done            INTEGER NOT NULL DEFAULT 0,
    confirm_between INTEGER NOT NULL,
    created_by      TEXT NOT NULL,
    created_at      INTEGER NOT NULL
);

CREATE INDEX queue_entries_machine ON queue_entries(machine_id, position);

CREATE TABLE machine_queues (
    machine_id INTEGER PRIMARY KEY REFERENCES machines(id) ON DELETE CASCADE,
    state      TEXT NOT NULL CHECK (state IN ('idle','waiting_confirm','running','held')),
    reason     TEXT,
    entry_id   INTEGER,
    run_id     INTEGER,
    updated_at INTEGER NOT NULL
);

CREATE TABLE part_records (
    id                INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id            INTEGER NOT NULL UNIQUE,
    job_id            INTEGER NOT NULL,
    machine_id        INTEGER NOT NULL,
    machine_name      TEXT NOT NULL,
    node              TEXT,
    program_name      TEXT NOT NULL,
    program_sha256    TEXT NOT NULL,
    work_offset       TEXT NOT NULL,
    work_zero         TEXT,
    part_zero         TEXT,
    tool_table        TEXT NOT NULL,
    tool_table_sha256 TEXT NOT NULL,
    operators         TEXT NOT NULL,
    confirmations     TEXT NOT NULL,
    outcome           TEXT NOT NULL CHECK (outcome IN ('completed','failed','cancelled','interrupted')),
    message           TEXT,
    line_count        INTEGER NOT NULL,
    from_line         INTEGER,
    last_line         INTEGER NOT NULL,
    lines_run         INTEGER NOT NULL,
    estimate_s        REAL,
    actual_s          REAL,
    started_at        INTEGER,
    ended_at          INTEGER NOT NULL
);

CREATE INDEX part_records_ended ON part_records(ended_at, id);

CREATE INDEX part_records_machine ON part_records(machine_id, ended_at, id);

CREATE INDEX part_records_job ON part_records(job_id, ended_at, id);

CREATE TABLE machine_states (
    id         INTEGER PRIMARY KEY AUTOINCREMENT,
    machine_id INTEGER NOT NULL,
    state      TEXT NOT NULL CHECK (state IN ('cutting','idle','held','alarm','unresponsive','offline')),
    since      INTEGER NOT NULL
);

CREATE INDEX machine_states_since ON machine_states(machine_id, since);

CREATE TABLE machine_counters (
    machine_id  INTEGER PRIMARY KEY,
    spindle_ms  INTEGER NOT NULL DEFAULT 0,
    motion_ms   INTEGER NOT NULL DEFAULT 0,
    distance_x  REAL NOT NULL DEFAULT 0,
    distance_y  REAL NOT NULL DEFAULT 0,
    distance_z  REAL NOT NULL DEFAULT 0,
    distance_a  REAL NOT NULL DEFAULT 0,
    jobs        INTEGER NOT NULL DEFAULT 0,
    updated_at  INTEGER NOT NULL
);

CREATE TABLE maintenance_marks (
    machine_id  INTEGER NOT NULL,
    name        TEXT NOT NULL,
    done_value  REAL NOT NULL DEFAULT 0,
    due_raised  INTEGER NOT NULL DEFAULT 0,
    done_at     INTEGER,
    done_by     TEXT,
    PRIMARY KEY (machine_id, name)
);

INSERT INTO event_retention VALUES(1,0);

INSERT INTO store_probe VALUES(1,0);
