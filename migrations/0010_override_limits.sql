-- Overrides (issue 26): the range of feed, spindle and rapid override an operator may set on
-- this machine, percent. A rapid override is at most 100 (the machine's rapid rate).
ALTER TABLE machines ADD COLUMN feed_override_min REAL NOT NULL DEFAULT 10.0;
ALTER TABLE machines ADD COLUMN feed_override_max REAL NOT NULL DEFAULT 200.0;
ALTER TABLE machines ADD COLUMN spindle_override_min REAL NOT NULL DEFAULT 50.0;
ALTER TABLE machines ADD COLUMN spindle_override_max REAL NOT NULL DEFAULT 150.0;
ALTER TABLE machines ADD COLUMN rapid_override_min REAL NOT NULL DEFAULT 25.0;
