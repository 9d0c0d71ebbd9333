-- shapeseek PostgreSQL schema, version 2: the ingest jobs of the JetStream work queue
-- (src/queue/). A serving node started with `--queue` stores an upload here (one committed row)
-- before it publishes the job; a worker analyses it, inserts the shape (idempotent by sha256)
-- and marks the job done, or records the error (a dead letter) when the input always fails.

CREATE TABLE jobs (
    -- From shape_id_seq: the shape is stored under the job's id.
    id               bigint  PRIMARY KEY,
    -- SHA-256 of the upload: twin uploads share one job.
    sha256           bytea   NOT NULL CHECK (octet_length(sha256) = 32),
    name             text,
    tags             text[]  NOT NULL,
    -- Format hint of the upload (Content-Type, ?format=, extension), if any.
    format_hint      text,
    -- The upload, until the job is done (then the stored original is in `meshes`).
    upload           bytea,
    state            text    NOT NULL CHECK (state IN ('pending', 'done', 'failed')),
    -- Deliveries a worker started.
    attempts         integer NOT NULL DEFAULT 0,
    -- The stored shape; deleting the shape deletes its job (a re-upload makes a new one).
    shape_id         bigint  REFERENCES shapes (id) ON DELETE CASCADE,
    -- The dead letter: the refusal's HTTP status, stable code and message.
    error_status     integer,
    error_code       text,
    error_message    text,
    created_unix_ms  bigint  NOT NULL,
    updated_unix_ms  bigint  NOT NULL,
    CONSTRAINT jobs_sha256_key UNIQUE (sha256)
);
ALTER TABLE jobs ALTER COLUMN upload SET STORAGE EXTERNAL;
