-- Pauses and tool changes (issue 26) and the tool length setter (issue 25): per machine, the
-- optional stop switch, what M6 does, where tools are changed and where the setter is. One row
-- for a machine whose settings were changed from the defaults; `settings` is a JSON object the
-- server checks before storing. `setter_reference_z` is the machine Z at which the reference
-- tool tripped the setter (tool lengths are measured from it); cleared when the setter moves.
CREATE TABLE machine_run_settings (
    machine_id         INTEGER PRIMARY KEY REFERENCES machines(id) ON DELETE CASCADE,
    settings           TEXT NOT NULL,
    setter_reference_z REAL,
    updated_at         INTEGER NOT NULL
);
