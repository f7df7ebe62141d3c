# Two commands for a new user: `make serve` and `make test` (the tests, then the documentation site
# built with --strict). Both are idempotent: the venv and the installs are redone only when
# pyproject.toml or constraints.txt change.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
# torch's CPU build comes from PyTorch's own index (PyPI's Linux torch is the multi-GB CUDA build);
# `make test TORCH_INDEX=URL` points elsewhere (a mirror), and a machine without it uses what pip has.
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
PIP    := $(PY) -m pip install --disable-pip-version-check -q -c constraints.txt --retries 2
TORCH  := --extra-index-url $(TORCH_INDEX)
HOST   := $(or $(SVRNET_HOST),127.0.0.1)
PORT   := $(or $(SVRNET_PORT),8000)
# The tests run in one process per core, at most 4 (each holds its models and fixtures: about 3 GB at
# most); `make test PYTEST_WORKERS=0` runs them in this process alone.
PYTEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); [ $$n -gt 4 ] && n=4; echo $$n)

.PHONY: serve test install-server install-dev install-queue bench cli-docs config-docs clean

$(PY):   # a venv made without pip (Debian without python3-venv) is removed, not kept half-made
	$(PYTHON) -m venv $(VENV) && $(PY) -m pip --version >/dev/null || { rm -rf $(VENV); exit 1; }

$(VENV)/.server-installed: $(PY) pyproject.toml constraints.txt   # the server and the svrnet command
	$(PIP) -e ".[server,client]"
	touch $@

$(VENV)/.dev-installed: $(PY) pyproject.toml constraints.txt
	$(PIP) $(TORCH) -e ".[dev]"
	touch $@ $(VENV)/.server-installed

$(VENV)/.queue-installed: $(VENV)/.server-installed   # the Redis job back-end (docs/deployment.md)
	$(PIP) -e ".[server,client,queue]"
	touch $@

install-server: $(VENV)/.server-installed
install-dev: $(VENV)/.dev-installed
install-queue: $(VENV)/.queue-installed

serve: install-server
	SVRNET_HOST=$(HOST) SVRNET_PORT=$(PORT) $(VENV)/bin/svrnet-server

test: install-dev
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) $(PYTEST_ARGS)
	site=$$(mktemp -d) && NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -q -d $$site; built=$$?; rm -rf $$site; exit $$built   # a folder of its own: checkouts side by side build apart

cli-docs: install-dev   # docs/cli.md, the reference of every svrnet command, from the CLI itself
	$(PY) -m typer client.cli utils docs --name svrnet --title "Command line: svrnet" --output docs/cli.md

config-docs: install-dev   # docs/configuration.md's table of every SVRNET_* setting, from the settings themselves
	$(PY) -m tools.settings_docs

bench: install-dev
	$(PY) benchmarks/se3_bench.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
