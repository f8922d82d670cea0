# calibconv: two commands on a fresh machine, `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
# The venv (4.7 GB) lives in a per-user cache keyed by the hash of requirements.txt and is
# linked as .venv, so fresh clones (CI) reuse it; a fresh machine builds it from nothing.
REQ_HASH := $(shell sha256sum requirements.txt | cut -c1-16)
VENV_CACHE ?= $(HOME)/.cache/calibconv/venv-$(REQ_HASH)
STAMP := $(VENV_CACHE)/.complete

.PHONY: setup test demo study bench fixtures lint gpu-build

# Always runs: builds the venv of this requirements.txt's hash if the cache lacks it, and points
# .venv at it (a checkout whose .venv links an older venv switches when requirements.txt changes).
setup:
	@if [ ! -f "$(STAMP)" ]; then \
	  echo "setup: creating $(VENV_CACHE) (pip install torch==2.13.0 and oracles; ~5 GB)"; \
	  rm -rf "$(VENV_CACHE)"; mkdir -p "$(dir $(VENV_CACHE))"; \
	  $(PYTHON) -m venv "$(VENV_CACHE)" && \
	  "$(VENV_CACHE)/bin/pip" install --quiet --upgrade pip && \
	  "$(VENV_CACHE)/bin/pip" install --quiet -r requirements.txt && \
	  ln -sfn "$$("$(VENV_CACHE)/bin/python" -c 'import os, torch; print(os.path.dirname(torch.__file__))')" "$(VENV_CACHE)/libtorch" && \
	  touch "$(STAMP)"; \
	fi
	@if [ "$$(readlink .venv)" != "$(VENV_CACHE)" ]; then rm -rf .venv; ln -sfn "$(VENV_CACHE)" .venv; fi
	@test -f .venv/.complete

# Every Rust test of the crate and of crates/geometry; the Python package's crate is left out of
# both cargo commands (it has no Rust tests) because Cargo unifies dependency features over the
# selected packages: with it (pyo3, numpy) serde, tch and calibconv itself built a second time,
# 4.4 of the 14 build minutes on a fresh 2-core machine. Without it both commands, and `make
# demo`'s `cargo build --release`, share one set of artifacts (Cargo.toml names bitflags' `std`
# feature for the same reason).
# Then the Python package (python/): built from this checkout into the venv (maturin from
# requirements.txt, no download), and its pytest suite against the binary built above; then the
# tests of the Python tools (tools/test_*.py).
CARGO_TESTED := --workspace --exclude calibconv-python
test: setup
	cargo build --release --all-targets $(CARGO_TESTED)
	cargo test --release $(CARGO_TESTED)
	PATH="$(CURDIR)/.venv/bin:$$PATH" .venv/bin/pip install --quiet --no-build-isolation ./python
	.venv/bin/python -m pytest -q python/tests tools/test_*.py

# The paper's experiments end to end on the embedded data (`quick` profile): synthesise the data
# sets (data/synth-quick.toml: 64 px, 160 test images per set from panoramas not used in
# training), run the sweep with its three seeds (per seed: 2 baselines, 10 fine-tunings, in
# results/quick/seed-S/), write the report and print its verdict table.
# Re-running skips what is complete and resumes what was interrupted.
DEMO_JOBS ?= 2
demo: setup
	cargo build --release
	@start=$$(date +%s); \
	./target/release/calibconv synth --config data/synth-quick.toml && \
	sweep_start=$$(date +%s) && \
	./target/release/calibconv sweep experiments/paper --profile quick --jobs $(DEMO_JOBS) --threads 1; \
	status=$$?; sweep_s=$$(( $$(date +%s) - $${sweep_start:-$$start} )); \
	./target/release/calibconv kernels --camera data/cameras/f195.toml --out results/quick/kernels_f195.png >/dev/null && \
	./target/release/calibconv report results/quick >/dev/null || status=1; \
	if [ -f results/quick/verdict.md ]; then echo; cat results/quick/verdict.md; echo; fi; \
	echo "make demo: synth + sweep + report in $$(( $$(date +%s) - start )) s (sweep $$sweep_s s; exit status $$status)"; \
	echo "report: $(CURDIR)/results/quick/REPORT.md"; \
	exit $$status

# The study (experiments/paper/profiles/study.toml + experiments/fov): 160 px data sets, 3 seeds,
# ~2 h on 2 cores; resumable (run it again to continue). Results: results/study, report: docs/study.
study: setup
	cargo build --release
	bash tools/study.sh

bench: setup
	cargo run --release -- bench

# calibconv for the GPU machine's torch 2.11 (tch 0.24), in target/gpu/ (binary + CUDA test
# executable); its own venv and lock file (tools/gpu/Cargo.lock), main's build untouched.
# Not part of `make test` (it downloads 4.6 GB the first time). See tools/gpu/build.sh.
gpu-build:
	bash tools/gpu/build.sh

fixtures: setup
	.venv/bin/python tools/make_fixtures.py tests/golden
	.venv/bin/python tools/make_unet_fixture.py tests/golden

lint: setup
	cargo fmt --all --check
	cargo clippy --release --all-targets --workspace -- -D warnings
	RUSTDOCFLAGS="-D warnings" cargo doc --no-deps --workspace --exclude calibconv-python
