-- Several nodes on one store (issue 16): each process is a node; machines and pendants belong
-- to the node that drives them. Kept in step with postgres/0006_nodes.sql.

CREATE TABLE nodes (
    name          TEXT PRIMARY KEY,
    -- Where other nodes reach it (forwarded requests), e.g. http://hall2.lan:7878.
    url           TEXT NOT NULL,
    version       TEXT NOT NULL,
    started_at    INTEGER NOT NULL,
    heartbeat_at  INTEGER NOT NULL,
    -- JSON object: machine id -> that machine's last status, written with each heartbeat, so
    -- the other nodes list remote machines without asking.
    machines      TEXT NOT NULL DEFAULT '{}'
);

-- NULL: created before nodes existed; the first node to start claims it.
ALTER TABLE machines ADD COLUMN node TEXT;
ALTER TABLE pendants ADD COLUMN node TEXT;

-- The secret nodes authenticate forwarded requests with: made once by the first node, read by
-- every node (whoever can read the store is already trusted with everything in it).
CREATE TABLE cluster (
    id           INTEGER PRIMARY KEY CHECK (id = 1),
    node_secret  TEXT NOT NULL
);

-- Programs by content (sha256), in chunks, so any node can run or show any job's program.
CREATE TABLE program_chunks (
    sha256  TEXT NOT NULL,
    seq     INTEGER NOT NULL,
    data    BLOB NOT NULL,
    PRIMARY KEY (sha256, seq)
);

-- The node an event happened on: each node's webhooks and MQTT bridge send only their own.
ALTER TABLE events ADD COLUMN node TEXT;
