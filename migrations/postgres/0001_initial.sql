-- shapeseek PostgreSQL schema, version 1: the same content as the sled index's version 2
-- (migrations/0001_initial.md, 0002_payloads.md). Applied by src/storage/pg_migrate.rs in one
-- transaction, which also records the version in `schema_version`.

-- Ids: the API shows them as 16 lower-case hex digits of this counter (like sled's generate_id).
CREATE SEQUENCE shape_id_seq AS bigint MINVALUE 0 START WITH 0;

CREATE TABLE shapes (
    id              bigint  PRIMARY KEY,
    -- SHA-256 of the original upload: the idempotency key.
    sha256          bytea   NOT NULL CHECK (octet_length(sha256) = 32),
    name            text    NOT NULL,
    tags            text[]  NOT NULL,
    spec_key        text    NOT NULL,
    created_unix_ms bigint  NOT NULL,
    -- The full ShapeRecord as the sled index stores it (JSON text kept as written).
    record          json    NOT NULL,
    CONSTRAINT shapes_sha256_key UNIQUE (sha256)
);
CREATE INDEX shapes_tags_idx ON shapes USING gin (tags);

-- Large values in their own tables: listing and signature scans never touch the meshes.
CREATE TABLE meshes (
    id      bigint PRIMARY KEY REFERENCES shapes (id) ON DELETE CASCADE,
    content bytea  NOT NULL
);
CREATE TABLE signatures (
    id      bigint PRIMARY KEY REFERENCES shapes (id) ON DELETE CASCADE,
    content bytea  NOT NULL
);
CREATE TABLE payloads (
    id      bigint PRIMARY KEY REFERENCES shapes (id) ON DELETE CASCADE,
    content bytea  NOT NULL
);
-- Signatures and payloads are float arrays that do not compress: store them uncompressed.
ALTER TABLE signatures ALTER COLUMN content SET STORAGE EXTERNAL;
ALTER TABLE payloads ALTER COLUMN content SET STORAGE EXTERNAL;

CREATE TABLE meta (
    key   text  PRIMARY KEY,
    value bytea NOT NULL
);

-- Exactly one row. Recalibration takes `SELECT ... FOR UPDATE` on it (the cluster-wide lock) and
-- writes the next epoch in the same transaction. epoch 0 = never calibrated.
CREATE TABLE calibration (
    singleton     boolean     PRIMARY KEY DEFAULT true CHECK (singleton),
    epoch         bigint      NOT NULL,
    calibrated_on bigint,
    body          json,
    updated_at    timestamptz
);
INSERT INTO calibration (singleton, epoch) VALUES (true, 0);
