-- Job queues per machine (issue 28): entries of N parts of a job, run one after another, with
-- an operator's confirmation between parts when `confirm_between` is 1. An entry leaves the
-- table when its last part completed.
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

-- Where each machine's queue is: `idle`, `waiting_confirm` (the next part waits for an
-- operator), `running` (`run_id` is a part of `entry_id`), `held` (`reason`; until released).
-- Stored, so a restart or a move to another node finds it as it was.
CREATE TABLE machine_queues (
    machine_id INTEGER PRIMARY KEY REFERENCES machines(id) ON DELETE CASCADE,
    state      TEXT NOT NULL CHECK (state IN ('idle','waiting_confirm','running','held')),
    reason     TEXT,
    entry_id   INTEGER,
    run_id     INTEGER,
    updated_at INTEGER NOT NULL
);
