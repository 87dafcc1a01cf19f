# `make demo` and `make test` each do all set-up, idempotently.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

.PHONY: demo test setup syslibs clean bench

setup: syslibs $(STAMP)

# Open3D's wheel links against libusb-1.0; install it only when missing.
syslibs:
	@ldconfig -p | grep -q libusb-1.0 || { \
	  echo "installing libusb-1.0-0 (needed by Open3D)"; \
	  (apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null) || \
	  (sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0 >/dev/null); }

# pip's output goes to .venv/install.log and is shown only when the install fails. constraints.txt pins
# every dependency to the versions the tests last passed with (a new release once changed a result).
$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || { echo "creating $(VENV)"; $(PY) -m venv $(VENV); }
	@echo "installing crossview and its dependencies into $(VENV) (log: $(VENV)/install.log)"
	@{ $(BIN)/python -m pip install -q --upgrade pip && \
	   $(BIN)/python -m pip install -q -c constraints.txt -e '.[dev]'; } > $(VENV)/install.log 2>&1 || \
	  { cat $(VENV)/install.log; echo "install failed (see above)"; exit 1; }
	@touch $(STAMP)

demo: setup
	@$(BIN)/crossview demo

# CI also installs Chromium so the report's screenshot test runs instead of skipping.
test: setup
	@if [ "$$CI" = "true" ] && ! command -v chromium >/dev/null; then \
	  echo "installing chromium (report screenshot test)"; \
	  apt-get update -qq && apt-get install -y -qq chromium >/dev/null || echo "chromium not installed: that test will skip"; fi
	@$(BIN)/python -m pytest -q tests

bench: setup
	@for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) out data/demo
