-- The part zero a controller reported when a run started (JSON {"x","y","z","a"}), so a
-- resume can check the controller still reports the same one (kawasaki-as, issue 6).
ALTER TABLE job_runs ADD COLUMN part_zero TEXT;
