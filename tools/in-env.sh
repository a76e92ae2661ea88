#!/usr/bin/env bash
# Set up everything rtval needs on a fresh Debian machine, then run the given command inside
# that environment:   tools/in-env.sh rtval validate    |    tools/in-env.sh python -m pytest
#  1. an LLVM that Dr.Jit can use (>= 16; Debian 12's LLVM 15 aborts Dr.Jit kernels),
#  2. a virtual environment (.venv, unless one is already active) with rtval installed,
#  3. when the command runs the tests (python -m pytest): Chromium and its driver, for the
#     HTML report's browser test (tests/test_html_report.py).
set -euo pipefail
here=$PWD                   # the command runs here: its relative paths are the caller's
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"

sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
apt_updated=""
apt_install() {
    [ -n "$apt_updated" ] || { $sudo apt-get update -qq >&2; apt_updated=1; }
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$@" >&2
}

# (grep reads to the end, not -q: under pipefail an early exit of grep -q can kill ldconfig
# with SIGPIPE and fail the pipeline although the library is there)
have_llvm() { ldconfig -p 2>/dev/null |
              grep -E 'libLLVM(-(1[6-9]|[2-9][0-9])|\.so\.(1[6-9]|[2-9][0-9]))' >/dev/null; }
if ! have_llvm; then
    echo "in-env: installing libllvm19 (Dr.Jit needs LLVM >= 16)" >&2
    apt_install libllvm19
    have_llvm || { echo "in-env: libllvm19 did not install; Dr.Jit cannot run" >&2; exit 1; }
fi

if [ -n "${VIRTUAL_ENV:-}" ]; then
    venv="$VIRTUAL_ENV"
else
    venv="$root/.venv"
    if [ ! -x "$venv/bin/python" ]; then
        # Debian's python3 makes venvs only with python3-venv (ensurepip) installed
        if ! python3 -c 'import ensurepip' 2>/dev/null; then
            echo "in-env: installing python3-venv" >&2
            apt_install python3-venv
        fi
        python3 -m venv "$venv"
    fi
fi
# reinstall only when the project's metadata changed
stamp="$venv/.rtval-installed"
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "in-env: installing rtval and its dependencies into $venv" >&2
    "$venv/bin/python" -m pip install -q --disable-pip-version-check -e ".[test]" >&2
    echo "$want" > "$stamp"
fi

# the headless browser the report tests drive; only when the tests are what runs
case "$*" in
    "python -m pytest"|"python -m pytest "*|"python3 -m pytest"|"python3 -m pytest "*|pytest|"pytest "*)
        if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
            echo "in-env: installing chromium and chromium-driver (the HTML report's browser" \
                 "test)" >&2
            apt_install chromium chromium-driver ||
                echo "in-env: chromium did not install; the browser test will be skipped" >&2
        fi ;;
esac

[ $# -gt 0 ] || exit 0
export PATH="$venv/bin:$PATH" VIRTUAL_ENV="$venv"
cd "$here"
exec "$@"
