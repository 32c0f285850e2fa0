#!/usr/bin/env bash
# Make a docker engine and docker compose available on this machine (idempotent; `make docker-setup`).
#
# * Installs Debian's docker.io, docker-compose (v1) and debootstrap (for the offline base image) with
#   apt-get when they are missing. A machine whose engine already answers `docker info` (a laptop with
#   Docker Desktop or docker-ce) gets no engine package, only what else is missing.
# * Starts dockerd in the background when `docker info` fails (log: $HAA_DOCKERD_LOG, default
#   /tmp/dockerd.log): storage driver overlay2 if an overlay mount works here, else vfs; iptables and the
#   default bridge are switched off only when this machine cannot do them. The engine is started with
#   --ip-forward=false --ip-masq=false: containers reach each other and the host (published ports), and
#   nothing beyond it.
# * Waits until `docker info` succeeds ($HAA_DOCKERD_WAIT seconds, default 60).
#
# Environment: HAA_DOCKER_STORAGE_DRIVER (force a driver), HAA_DOCKERD_ARGS (replace the network flags
# above), HAA_DOCKERD_LOG, HAA_DOCKERD_WAIT, HAA_SKIP_APT=1 (never call apt-get).
# Findings about what this sandbox allows: docs/containers.md.
set -euo pipefail

LOG=${HAA_DOCKERD_LOG:-/tmp/dockerd.log}
WAIT=${HAA_DOCKERD_WAIT:-60}
DATA_ROOT=/var/lib/docker

say() { echo "docker-setup: $*"; }
warn() { echo "docker-setup: warning: $*" >&2; }
die() {
    echo "docker-setup: error: $*" >&2
    exit 1
}
have() { command -v "$1" >/dev/null 2>&1; }

SUDO=()
if [ "$(id -u)" != 0 ]; then
    if have sudo; then SUDO=(sudo); else SUDO=(false-no-root); fi
fi
as_root() {
    if [ "${SUDO[0]:-}" = false-no-root ]; then
        die "need root for: $* (run as root, or install sudo)"
    fi
    "${SUDO[@]}" "$@"
}

engine_up() { docker info >/dev/null 2>&1; }

compose_cmd() {
    if docker compose version >/dev/null 2>&1; then
        echo "docker compose"
    elif have docker-compose; then
        echo "docker-compose"
    fi
}

# ---------------------------------------------------------------- packages
install_packages() {
    local pkgs=()
    if ! have docker || { ! engine_up && ! have dockerd; }; then pkgs+=(docker.io); fi
    if [ -z "$(compose_cmd)" ] && ! have docker-compose; then pkgs+=(docker-compose); fi
    if ! have debootstrap; then pkgs+=(debootstrap); fi
    [ ${#pkgs[@]} -eq 0 ] && return 0
    if [ "${HAA_SKIP_APT:-0}" = 1 ]; then
        warn "missing ${pkgs[*]} and HAA_SKIP_APT=1: not installing"
        return 0
    fi
    if ! have apt-get; then
        warn "missing ${pkgs[*]} and no apt-get here: install them with this system's package manager"
        return 0
    fi
    say "installing ${pkgs[*]} (apt-get)"
    local apt=(env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${pkgs[@]}")
    if ! as_root "${apt[@]}" >/tmp/haa-apt.log 2>&1; then
        say "apt-get install failed; refreshing the package lists and retrying"
        as_root env DEBIAN_FRONTEND=noninteractive apt-get update -q >>/tmp/haa-apt.log 2>&1 || true
        as_root "${apt[@]}" >>/tmp/haa-apt.log 2>&1 || {
            tail -n 20 /tmp/haa-apt.log >&2
            die "apt-get install ${pkgs[*]} failed (full log: /tmp/haa-apt.log)"
        }
    fi
}

# ---------------------------------------------------------------- probes of what this machine allows
probe_overlay() {
    # An overlay mount on the filesystem that will hold /var/lib/docker.
    as_root mkdir -p "$DATA_ROOT"
    local d ok=1
    d=$(as_root mktemp -d "$DATA_ROOT/.haa-ovl-probe.XXXXXX")
    as_root mkdir -p "$d/l" "$d/u" "$d/w" "$d/m"
    if as_root mount -t overlay overlay -o "lowerdir=$d/l,upperdir=$d/u,workdir=$d/w" "$d/m" 2>/dev/null; then
        as_root umount "$d/m" || true
        ok=0
    fi
    as_root rm -rf --one-file-system "$d"
    return $ok
}

probe_iptables() {
    have iptables && as_root iptables -t nat -L -n >/dev/null 2>&1 && as_root iptables -t filter -L -n >/dev/null 2>&1
}

probe_bridge() {
    local br=haaprobe$$
    as_root ip link add name "$br" type bridge 2>/dev/null || return 1
    as_root ip link del "$br" 2>/dev/null || true
}

# ---------------------------------------------------------------- dockerd
dockerd_pid() {
    local pid
    pid=$(cat /var/run/docker.pid 2>/dev/null) || return 1
    [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null && echo "$pid"
}

wait_engine() { # $1 = pid of the dockerd we started (or empty); returns 0 up, 1 died, 2 timed out
    local pid=$1 i
    for ((i = 0; i < WAIT * 4; i++)); do
        engine_up && return 0
        if [ -n "$pid" ] && ! kill -0 "$pid" 2>/dev/null; then return 1; fi
        sleep 0.25
    done
    return 2
}

show_errors() { # the errors dockerd logged since our last start (else the last lines of the log)
    local run errs
    run=$(awk '/^=== .* docker-setup: dockerd/ { buf = "" } { buf = buf $0 "\n" } END { printf "%s", buf }' "$LOG")
    errs=$(grep -E 'level=(error|fatal)|^failed to start' <<<"$run" | tail -n 8 || true)
    if [ -n "$errs" ]; then echo "$errs" >&2; else tail -n 15 <<<"$run" >&2; fi
    echo "(full log: $LOG)" >&2
}

start_dockerd() { # $1 = storage driver
    local driver=$1 args=()
    args+=(--storage-driver="$driver")
    if [ -n "${HAA_DOCKERD_ARGS+x}" ]; then
        read -r -a extra <<<"$HAA_DOCKERD_ARGS"
        args+=("${extra[@]}")
    else
        args+=(--ip-forward=false --ip-masq=false)
        if ! probe_iptables; then
            warn "iptables does not work here: starting dockerd with --iptables=false (published ports use docker-proxy)"
            args+=(--iptables=false)
        fi
        if ! probe_bridge; then
            warn "cannot create a bridge here: starting dockerd with --bridge=none; compose networks will not work"
            args+=(--bridge=none)
        fi
    fi
    say "starting dockerd ${args[*]} (log: $LOG)"
    echo "=== $(date -u +%FT%TZ) docker-setup: dockerd ${args[*]}" >>"$LOG"
    # setsid + nohup: dockerd outlives this script, make and the shell that ran them.
    [ "${SUDO[0]:-}" = false-no-root ] && die "need root to start dockerd"
    (exec "${SUDO[@]}" setsid nohup dockerd "${args[@]}" >>"$LOG" 2>&1 </dev/null) &
    local launcher=$!
    local t0=$SECONDS rc=0
    sleep 0.5
    wait_engine "$(dockerd_pid || echo "$launcher")" || rc=$?
    case $rc in
        0) say "dockerd is up after $((SECONDS - t0)) s (storage driver $driver)" ;;
        1) warn "dockerd exited during start-up:" && show_errors ;;
        2) warn "dockerd did not answer within ${WAIT} s:" && show_errors ;;
    esac
    return $rc
}

# ---------------------------------------------------------------- main
[ -n "${DOCKER_HOST:-}" ] && say "note: DOCKER_HOST=$DOCKER_HOST (the engine checked and started is the local one only if that points here)"

install_packages
have docker || die "no docker client: install docker.io (Debian) or docker-ce"

if engine_up; then
    say "docker engine already running ($(docker info --format '{{.ServerVersion}}, storage {{.Driver}}' 2>/dev/null))"
else
    if pid=$(dockerd_pid); then
        say "dockerd (pid $pid) is running but not answering yet; waiting"
        wait_engine "$pid" || die "dockerd pid $pid does not answer \`docker info\` (log: $LOG; stop it with: kill $pid)"
    else
        have dockerd || die "no dockerd on this machine and \`docker info\` fails: install docker.io or start your engine"
        if [ ! -d /sys/fs/cgroup ] || [ -z "$(ls -A /sys/fs/cgroup 2>/dev/null)" ]; then
            warn "/sys/fs/cgroup is empty: dockerd needs cgroups mounted (cgroupfs-mount)"
        fi
        driver=${HAA_DOCKER_STORAGE_DRIVER:-}
        if [ -z "$driver" ]; then
            if probe_overlay; then driver=overlay2; else
                warn "overlay mounts do not work on $DATA_ROOT here: using the vfs storage driver (slow, big)"
                driver=vfs
            fi
        fi
        if ! start_dockerd "$driver"; then
            # The first attempt may have left a dockerd that is still starting or stuck: stop only that one.
            if pid=$(dockerd_pid); then
                as_root kill "$pid" 2>/dev/null || true
                sleep 2
            fi
            if [ "$driver" = overlay2 ] && [ -z "${HAA_DOCKER_STORAGE_DRIVER:-}" ]; then
                warn "retrying dockerd with the vfs storage driver"
                start_dockerd vfs || die "dockerd did not start with overlay2 nor vfs (log: $LOG)"
            else
                die "dockerd did not start (log: $LOG)"
            fi
        fi
    fi
fi

engine_up || die "\`docker info\` fails"
cc=$(compose_cmd)
if [ -z "$cc" ]; then
    warn "neither \`docker compose\` (v2) nor docker-compose (v1) is available"
else
    say "compose: $cc ($($cc version --short 2>/dev/null || $cc version 2>/dev/null | head -n 1))"
fi
say "ready: $(docker info --format 'engine {{.ServerVersion}}, storage {{.Driver}}, cgroup v{{.CgroupVersion}} ({{.CgroupDriver}})' 2>/dev/null)"
