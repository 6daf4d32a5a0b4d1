-- Kept in step with ../0002_pendants.sql.
CREATE TABLE pendant_macros (
    pendant_id  BIGINT NOT NULL REFERENCES pendants(id) ON DELETE CASCADE,
    slot        BIGINT NOT NULL CHECK (slot BETWEEN 1 AND 4),
    action      TEXT NOT NULL,
    updated_at  BIGINT NOT NULL,
    PRIMARY KEY (pendant_id, slot)
);
