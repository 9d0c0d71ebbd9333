//! Cotangent Laplacian (stub, in progress).
