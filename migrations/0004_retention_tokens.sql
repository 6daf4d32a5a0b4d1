-- Tokens can expire and be listed and revoked by name; the event log can be pruned.

-- NULL: never expires / never used (last use is recorded at most once a minute).
ALTER TABLE tokens ADD COLUMN expires_at INTEGER;
ALTER TABLE tokens ADD COLUMN last_used_at INTEGER;
-- Names must be unique so `fresa token revoke NAME` means one token. Older databases may
-- hold repeats: every one but the oldest is renamed `NAME#ID` (shown by `fresa token list`).
UPDATE tokens SET name = name || '#' || id
 WHERE id NOT IN (SELECT MIN(id) FROM tokens GROUP BY name);
CREATE UNIQUE INDEX tokens_name ON tokens(name);

-- Retention deletes by age; without this index every pass would scan the whole log.
CREATE INDEX events_created ON events(created_at);
-- The highest event id retention has deleted: a replay asked to start before it has a gap,
-- and is told so (`resync`). One row.
CREATE TABLE event_retention (
    id              INTEGER PRIMARY KEY CHECK (id = 1),
    pruned_through  INTEGER NOT NULL
);
INSERT INTO event_retention (id, pruned_through) VALUES (1, 0);
