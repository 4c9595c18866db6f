# One local command mirrors CI: `make test` (what .ci/run calls).
CARGO ?= cargo

.PHONY: test venv fmt-check clippy unit doc run sim bench

## The whole suite, as CI runs it: Python peers, fmt, clippy, tests, docs.
test: venv fmt-check clippy unit doc

## Independent protocol peers (ur-rtde, pymodbus, python-can, mcap, OpenCV) into .venv.
venv:
	./scripts/setup_venv.sh

fmt-check:
	$(CARGO) fmt --all -- --check

clippy:
	$(CARGO) clippy --workspace --all-targets --locked -- -D warnings

unit:
	$(CARGO) test --workspace --locked

doc:
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --workspace --no-deps --locked

## The main job on the built-in simulated cell.
run:
	$(CARGO) run --release --locked -- run
