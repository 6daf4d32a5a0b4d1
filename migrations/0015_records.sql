-- The shop's records (issue 28, part 2).
--
-- A part record for every run that ended (completed, failed, cancelled): what was made, where,
-- with what and by whom, written once the run's end is stored (and rewritten if a failed run is
-- resumed and ends again: one record per run). No foreign keys: a record is history and stays
-- when its job or machine goes. JSON columns: `work_zero` and `part_zero` are {x,y,z,a} (machine
-- coordinates), `tool_table` the machine's tools at the end, `operators` the names who started,
-- resumed or confirmed the run, `confirmations` the queue's `queue.confirm` entries for it.
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
-- The list's filters (machine, job, time) each have an index that also orders the page.
CREATE INDEX part_records_ended ON part_records(ended_at, id);
CREATE INDEX part_records_machine ON part_records(machine_id, ended_at, id);
CREATE INDEX part_records_job ON part_records(job_id, ended_at, id);

-- A machine's state changes as the host saw them (one row per change: the state held from
-- `since` until the next row's `since`). States: cutting, idle, held, alarm, unresponsive,
-- offline.
CREATE TABLE machine_states (
    id         INTEGER PRIMARY KEY AUTOINCREMENT,
    machine_id INTEGER NOT NULL,
    state      TEXT NOT NULL CHECK (state IN ('cutting','idle','held','alarm','unresponsive','offline')),
    since      INTEGER NOT NULL
);
CREATE INDEX machine_states_since ON machine_states(machine_id, since);

-- Maintenance counters per machine; written only upwards (see store/records.rs).
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

-- Where each maintenance interval of a machine stands: the counter's value when it was last
-- done (its interval runs from there), and whether `machine.maintenance_due` was raised for the
-- current interval (so it is raised once per crossing, also across restarts).
CREATE TABLE maintenance_marks (
    machine_id  INTEGER NOT NULL,
    name        TEXT NOT NULL,
    done_value  REAL NOT NULL DEFAULT 0,
    due_raised  INTEGER NOT NULL DEFAULT 0,
    done_at     INTEGER,
    done_by     TEXT,
    PRIMARY KEY (machine_id, name)
);

-- The machine's maintenance intervals: a JSON array of {"name", "every_spindle_hours" |
-- "every_motion_hours" | "every_jobs"}.
ALTER TABLE machines ADD COLUMN maintenance TEXT NOT NULL DEFAULT '[]';
