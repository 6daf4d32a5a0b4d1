-- Kept in step with ../0008_unstored_lines.sql (issue 23).
ALTER TABLE job_runs ADD COLUMN unstored_line BIGINT;

CREATE TABLE store_probe (
    id    BIGINT PRIMARY KEY CHECK (id = 1),
    at_ms BIGINT NOT NULL
);
INSERT INTO store_probe (id, at_ms) VALUES (1, 0);
