-- Webhooks: URLs that receive signed JSON deliveries of persisted events (issue 17).

CREATE TABLE webhooks (
    id               INTEGER PRIMARY KEY,
    url              TEXT NOT NULL,
    -- JSON array of event types; `job` matches `job.*`; empty: every persisted event.
    events           TEXT NOT NULL DEFAULT '[]',
    -- The HMAC-SHA256 key. Kept in the clear because signing needs it; shown once at creation
    -- and never by the API again.
    secret           TEXT NOT NULL,
    created_by       TEXT NOT NULL,
    created_at       INTEGER NOT NULL,
    -- The last delivery: HTTP status (NULL: no answer), error, attempts it took, when it ended.
    last_status      INTEGER,
    last_error       TEXT,
    last_attempts    INTEGER NOT NULL DEFAULT 0,
    last_delivery_at INTEGER,
    delivered        INTEGER NOT NULL DEFAULT 0,
    failed           INTEGER NOT NULL DEFAULT 0
);
