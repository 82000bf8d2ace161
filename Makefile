# Two commands do all the set-up on a fresh machine with Python 3.11:
#   make demo   -- create .venv, install canrls, run the demo on the simulated drive
#   make test   -- create .venv, install canrls with its test extras, run the tests
#                  (the PostgreSQL tests install Debian's postgresql with apt-get as root)
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
BIN     = $(VENV)/bin

.PHONY: demo test bench target clean

# the C extensions are built by the install: rebuilt when their sources change
$(BIN)/.installed: pyproject.toml setup.py $(wildcard src/canrls/c/*.c src/canrls/c/*.h)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,report,fleet]'
	touch $@

demo: $(BIN)/.installed
	$(BIN)/canrls demo

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q

bench: $(BIN)/.installed
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python tools/bench_rls.py

# the C kernel (src/canrls/c) for a Cortex-M4: size, stack, the bare-metal example on
# QEMU mps2-an386 checked bit for bit against the Python FixedRLS, instructions per update
# (installs gcc-arm-none-eabi, libnewlib-arm-none-eabi, qemu-system-arm via apt-get as root)
target: $(BIN)/.installed
	$(BIN)/python tools/build_target.py --out build/target

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache
