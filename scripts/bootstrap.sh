# Sourced by ./run and ./test: create or refresh .venv with the project installed.
# Usage: bootstrap_venv [EXTRAS]   (e.g. bootstrap_venv test)
bootstrap_venv() {
  # two statements: in one `local a=.. b=$a`, $a would expand before a is set
  local extras="${1:-}"
  local stamp=".venv/.installed${extras:+-$extras}"
  if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
  fi
  # Reinstall only when pyproject.toml changed since the last install.
  if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e ".${extras:+[$extras]}"
    touch "$stamp"
  fi
  # numba kernels compiled once (the first time, ~20 s) or loaded from their cache (~1 s), so the
  # first replay does not stall on them and test workers do not compile them side by side
  .venv/bin/python -m estimators.kernel_warmup
}
