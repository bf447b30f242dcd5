#!/usr/bin/env bash
# Print the command that runs Python X.Y (the first argument): pythonX.Y on the PATH if
# it is that version, else pyenv's newest installed X.Y.* (pyenv's shim for a version
# that is installed but not selected), else nothing and exit status 1.
set -u
version="$1"
check="import sys; sys.exit(sys.version_info[:2] != tuple(int(p) for p in '$version'.split('.')))"
if command -v "python$version" >/dev/null 2>&1 && "python$version" -c "$check" 2>/dev/null; then
  echo "python$version"
  exit 0
fi
if command -v pyenv >/dev/null 2>&1; then
  installed=$(pyenv versions --bare 2>/dev/null | grep -E "^${version//./\\.}\.[0-9]+$" | sort -V | tail -n 1)
  if [ -n "$installed" ] && PYENV_VERSION="$installed" "python$version" -c "$check" 2>/dev/null; then
    echo "env PYENV_VERSION=$installed python$version"
    exit 0
  fi
fi
exit 1
