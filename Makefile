# Two commands do all the set-up on a fresh machine with Python 3.11:
#   make demo   -- create .venv, install canrls, run the demo on the simulated drive
#   make test   -- create .venv, install canrls with its test extras, run the tests
#                  (the PostgreSQL tests install Debian's postgresql with apt-get as root)
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
BIN     = $(VENV)/bin

.PHONY: demo test bench target clean

# the C extensions are built by the install: rebuilt when their sources change
$(BIN)/.installed: pyproject.toml setup.py $(wildcard src/canrls/c/*/*.c src/canrls/c/*/*.h)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,report,fleet]'
	touch $@

demo: $(BIN)/.installed
	$(BIN)/canrls demo

# two processes (pytest-xdist), each test file whole in one of them: its module fixtures
# built once, its tests in order
test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

bench: $(BIN)/.installed
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python tools/bench_rls.py

# the C for a Cortex-M4 on QEMU mps2-an386: the kernel (size, stack, a recorded log bit for
# bit against the Python FixedRLS, instructions per update) and the whole estimator of
# export-c at n = 4, 6, 8 (bit for bit; instructions per sample and per update, mean and
# worst over the whole log; .text at -O2 and -Os); docs/target.md has the figures
# (installs gcc, gcc-arm-none-eabi, libnewlib-arm-none-eabi, qemu-system-arm via apt-get
# as root)
target: $(BIN)/.installed
	$(BIN)/python tools/build_target.py --out build/target

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache
