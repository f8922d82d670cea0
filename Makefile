# calibconv: two commands on a fresh machine, `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
# The venv (4.7 GB) lives in a per-user cache keyed by the hash of requirements.txt and is
# linked as .venv, so fresh clones (CI) reuse it; a fresh machine builds it from nothing.
REQ_HASH := $(shell sha256sum requirements.txt | cut -c1-16)
VENV_CACHE ?= $(HOME)/.cache/calibconv/venv-$(REQ_HASH)
STAMP := $(VENV_CACHE)/.complete

.PHONY: setup test demo bench fixtures lint

setup: .venv/.complete

.venv/.complete: requirements.txt
	@if [ ! -f "$(STAMP)" ]; then \
	  echo "setup: creating $(VENV_CACHE) (pip install torch==2.13.0 and oracles; ~5 GB)"; \
	  rm -rf "$(VENV_CACHE)"; mkdir -p "$(dir $(VENV_CACHE))"; \
	  $(PYTHON) -m venv "$(VENV_CACHE)" && \
	  "$(VENV_CACHE)/bin/pip" install --quiet --upgrade pip && \
	  "$(VENV_CACHE)/bin/pip" install --quiet -r requirements.txt && \
	  ln -sfn "$$("$(VENV_CACHE)/bin/python" -c 'import os, torch; print(os.path.dirname(torch.__file__))')" "$(VENV_CACHE)/libtorch" && \
	  touch "$(STAMP)"; \
	fi
	@rm -rf .venv; ln -sfn "$(VENV_CACHE)" .venv
	@test -f .venv/.complete

test: setup
	cargo build --release --all-targets
	cargo test --release

demo: setup
	cargo build --release
	./target/release/calibconv demo

bench: setup
	cargo run --release -- bench

fixtures: setup
	.venv/bin/python tools/make_fixtures.py tests/golden
	.venv/bin/python tools/make_unet_fixture.py tests/golden

lint: setup
	cargo fmt --check
	cargo clippy --release --all-targets -- -D warnings
