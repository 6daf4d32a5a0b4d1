-- Kept in step with ../0011_run_settings.sql (issues 25 and 26).
CREATE TABLE machine_run_settings (
    machine_id         BIGINT PRIMARY KEY REFERENCES machines(id) ON DELETE CASCADE,
    settings           TEXT NOT NULL,
    setter_reference_z DOUBLE PRECISION,
    updated_at         BIGINT NOT NULL
);
