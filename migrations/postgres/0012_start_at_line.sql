-- Kept in step with ../0012_start_at_line.sql (issue 26).
ALTER TABLE job_runs ADD COLUMN from_line BIGINT;
ALTER TABLE machines ADD COLUMN safe_z_mm DOUBLE PRECISION;
