# Sourced by the scripts beside it, from the project's root: `venv_install EXTRAS` makes
# .venv once (with $PYTHON, else python3) and installs the project with those extras.
venv_install() {
    if [ ! -x .venv/bin/python ]; then
        "${PYTHON:-python3}" -m venv .venv
    fi
    .venv/bin/python -m pip install --quiet --upgrade pip
    .venv/bin/python -m pip install --quiet -e ".[$1]"
}
