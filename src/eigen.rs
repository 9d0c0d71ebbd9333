//! Eigensolver (stub, in progress).
