#!/bin/sh
# Entrypoint of the haa-hostd image: run haa-hostd with the container's arguments, or haa-sim when the first
# argument is `haa-sim` (compose.yaml's sim service).
# As PID 1 (`docker run` without --init) it runs under tini when the base has it, so that exited children
# are reaped; under `init: true` / `--init` docker's own init is PID 1 and the program is exec'd directly.
# haa-hostd handles SIGTERM itself (graceful leave).
prog=haa-hostd
if [ "${1:-}" = haa-sim ]; then
    prog=haa-sim
    shift
fi
# A raw `docker-compose up` before `make image` wrote compose/token: docker bind-mounts a missing source as a
# new empty directory, and every container would stop with a bare "Is a directory". Say what to do instead.
if [ -d /run/haa/token ]; then
    echo "$prog: error: token file /run/haa/token is a directory: compose/token did not exist when the" \
         "container was created, so docker made an empty directory in its place. Run \`make image\` (it replaces" \
         "that directory with the token), then \`docker-compose -f compose/compose.yaml up -d\` again." >&2
    exit 2
fi
if [ "$$" = 1 ] && command -v tini >/dev/null 2>&1; then
    exec tini -- "$prog" "$@"
fi
exec "$prog" "$@"
