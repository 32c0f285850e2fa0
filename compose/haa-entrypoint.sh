#!/bin/sh
# Entrypoint of the haa-hostd image: run haa-hostd with the container's arguments.
# As PID 1 (`docker run` without --init) it runs under tini when the base has it, so that exited children
# are reaped; under `init: true` / `--init` docker's own init is PID 1 and haa-hostd is exec'd directly.
# haa-hostd handles SIGTERM itself (graceful leave).
if [ "$$" = 1 ] && command -v tini >/dev/null 2>&1; then
    exec tini -- haa-hostd "$@"
fi
exec haa-hostd "$@"
