-- Pendant transport: what each pendant's macro keys (Fn + key = M1..M4) do.
-- `action` is JSON (see plugins/mpg-pendant/README.md), e.g. {"type":"command","command":"feed_hold"}.
CREATE TABLE pendant_macros (
    pendant_id  INTEGER NOT NULL REFERENCES pendants(id) ON DELETE CASCADE,
    slot        INTEGER NOT NULL CHECK (slot BETWEEN 1 AND 4),
    action      TEXT NOT NULL,
    updated_at  INTEGER NOT NULL,
    PRIMARY KEY (pendant_id, slot)
);
