-- Height maps (issue 25): a grid of surface heights probed over an area of a machine's work
-- coordinates, applied to a job's Z. `points` is a JSON array of nx * ny numbers, row by row
-- (Y from y0 up), each the work Z where the probe tripped, or null where the grid did not get
-- to (a map that was stopped or failed keeps what it probed and is never applied).
-- `offset_*`: the work zero in machine coordinates when it was probed (machine - work
-- position), so the map can be expressed in the work offset a job later starts in.
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

-- The height map a run was started with (kept as a number: the map may be deleted later; a
-- resume then refuses).
ALTER TABLE job_runs ADD COLUMN height_map_id INTEGER;
