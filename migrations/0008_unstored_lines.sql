-- A full or failing disk (issue 23).
-- `unstored_line`: set at start-up when the previous process stopped while lines of this run
-- were acknowledged only in memory (the database could not be written); the highest such line
-- it recorded. The stored `last_line` may then be behind what ran, so a resume needs the
-- operator to confirm the line. NULL: `last_line` is what the machine acknowledged.
ALTER TABLE job_runs ADD COLUMN unstored_line INTEGER;

-- One row the health monitor rewrites to learn whether the database takes writes again.
CREATE TABLE store_probe (
    id    INTEGER PRIMARY KEY CHECK (id = 1),
    at_ms INTEGER NOT NULL
);
INSERT INTO store_probe (id, at_ms) VALUES (1, 0);
