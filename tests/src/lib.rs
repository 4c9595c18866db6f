//! Shared helpers for the HIL regression tests in `tests/tests/`.
