//! Holder crate for KIWI's end-to-end tests (see `tests/tests/`); it has no library code.
