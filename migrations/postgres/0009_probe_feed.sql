-- Probing and touch-off (issue 25): the fastest feed a probing move may ask for on this machine,
-- mm/min. A probe that trips stops from this speed, so it is kept low by default.
ALTER TABLE machines ADD COLUMN max_probe_feed_mm_min DOUBLE PRECISION NOT NULL DEFAULT 300.0;
