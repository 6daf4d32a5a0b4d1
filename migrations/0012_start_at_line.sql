-- Start at a line (issue 26).
-- `from_line`: the line a run was started from (`POST /jobs/{id}/start {"from_line": N}`); NULL
-- for a run started from its first line. A resume of such a run goes on from the next
-- acknowledged line, but never from before this one (the lines before it never ran).
ALTER TABLE job_runs ADD COLUMN from_line INTEGER;
-- `safe_z_mm`: the machine Z (machine coordinates, mm) a start at a line or a resume goes up to
-- at least before it moves across to the start point; NULL: only the machine's own Z and the
-- highest Z of the program before the line count.
ALTER TABLE machines ADD COLUMN safe_z_mm REAL;
