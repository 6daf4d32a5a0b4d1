-- Kept in step with ../0004_retention_tokens.sql. (A new PostgreSQL store has no repeated token
-- names to rename.)
ALTER TABLE tokens ADD COLUMN expires_at BIGINT;
ALTER TABLE tokens ADD COLUMN last_used_at BIGINT;
CREATE UNIQUE INDEX tokens_name ON tokens(name);
CREATE INDEX events_created ON events(created_at);
CREATE TABLE event_retention (
    id              BIGINT PRIMARY KEY CHECK (id = 1),
    pruned_through  BIGINT NOT NULL
);
INSERT INTO event_retention (id, pruned_through) VALUES (1, 0);
