-- Each machine's tool table (issue 14): what G41/G42 D<n> offsets by, and the G43 length.
-- Millimetres. Replaced as a whole or one tool at a time through the API.

CREATE TABLE machine_tools (
    machine_id  INTEGER NOT NULL REFERENCES machines(id) ON DELETE CASCADE,
    tool        INTEGER NOT NULL CHECK (tool >= 0),
    diameter_mm REAL NOT NULL,
    length_mm   REAL NOT NULL DEFAULT 0,
    description TEXT NOT NULL DEFAULT '',
    updated_at  INTEGER NOT NULL,
    PRIMARY KEY (machine_id, tool)
);
