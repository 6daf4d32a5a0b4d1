-- Kept in step with ../0003_kawasaki.sql.
ALTER TABLE job_runs ADD COLUMN part_zero TEXT;
