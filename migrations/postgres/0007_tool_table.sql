-- Kept in step with ../0007_tool_table.sql (issue 14).
CREATE TABLE machine_tools (
    machine_id  BIGINT NOT NULL REFERENCES machines(id) ON DELETE CASCADE,
    tool        BIGINT NOT NULL CHECK (tool >= 0),
    diameter_mm DOUBLE PRECISION NOT NULL,
    length_mm   DOUBLE PRECISION NOT NULL DEFAULT 0,
    description TEXT NOT NULL DEFAULT '',
    updated_at  BIGINT NOT NULL,
    PRIMARY KEY (machine_id, tool)
);
