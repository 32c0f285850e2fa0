#!/usr/bin/env bash
# Build the haa-hostd image without any registry (`make image`).
#
# 1. Base image $HAA_BASE_IMAGE (default haa-base:bookworm), only if it is not present locally:
#    haa-base:* is made offline here: `debootstrap --variant=minbase bookworm` with python3 (3.11),
#    python3-venv, ca-certificates, iproute2, procps and tini into a temp dir, then `docker import`.
#    Any other name (e.g. python:3.11-slim on a machine with a registry) is pulled.
# 2. Wheelhouse compose/wheelhouse/ (gitignored): the haa wheel built from this working tree, and every
#    runtime dependency as cp311 manylinux x86_64 wheels fetched with `pip download` on the host (skipped
#    when the wheelhouse already satisfies them).
# 3. compose/token (gitignored): the cluster token, generated when missing; and compose/tls/hosts/hN (gitignored),
#    the empty mount points of the hosts' TLS directories (`haactl cluster up --compose --tls` fills them):
#    docker would otherwise create them, owned by root, at the first `up`.
# 4. `docker build --network none` of compose/Dockerfile -> $HAA_IMAGE (default haa-hostd:latest).
#
# Environment: HAA_BASE_IMAGE, HAA_IMAGE, PYTHON (host interpreter for pip, default python3),
# HAA_DEBIAN_MIRROR (debootstrap mirror; default: the bookworm source of this host's apt, else
# debootstrap's own default), HAA_REBUILD_BASE=1 (rebuild the base even if present).
# See docs/containers.md.
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
CTX=$ROOT/compose
WHEELHOUSE=$CTX/wheelhouse
TOKEN=$CTX/token
IMAGE=${HAA_IMAGE:-haa-hostd:latest}
BASE=${HAA_BASE_IMAGE:-haa-base:bookworm}
PYTHON=${PYTHON:-python3}
SUITE=bookworm
BASE_PACKAGES=python3,python3-venv,ca-certificates,iproute2,procps,tini

say() { echo "build-image: $*"; }
die() {
    echo "build-image: error: $*" >&2
    exit 1
}
have() { command -v "$1" >/dev/null 2>&1; }
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }

have docker || die "no docker client; run scripts/docker-setup.sh (make docker-setup)"
docker info >/dev/null 2>&1 || die "the docker engine does not answer \`docker info\`; run scripts/docker-setup.sh (make docker-setup)"
T_ALL=$(now)

# ---------------------------------------------------------------- 1. base image
debian_mirror() {
    # The URI this host's apt uses for Debian $SUITE (deb822 or one-line sources); empty if none.
    if [ -n "${HAA_DEBIAN_MIRROR:-}" ]; then
        echo "$HAA_DEBIAN_MIRROR"
        return
    fi
    local uris
    uris=$(
        for f in /etc/apt/sources.list.d/*.sources; do
            [ -r "$f" ] || continue
            awk -v suite="$SUITE" '
                BEGIN { RS = ""; FS = "\n" }
                {
                    uri = ""; ok = 0; en = 1
                    for (i = 1; i <= NF; i++) {
                        if ($i ~ /^URIs:/) { split(substr($i, 6), u, " "); uri = u[1] }
                        if ($i ~ /^Suites:/) { n = split(substr($i, 8), s, " "); for (j = 1; j <= n; j++) if (s[j] == suite) ok = 1 }
                        if ($i ~ /^Enabled: *no/) en = 0
                    }
                    if (ok && en && uri != "") print uri
                }' "$f"
        done
        cat /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null |
            awk -v suite="$SUITE" '$1 == "deb" { for (i = 2; i < NF; i++) if ($i !~ /^\[/ && $(i + 1) == suite) print $i }'
    )
    echo "${uris%%$'\n'*}"
}

umount_under() { # unmount everything mounted below $1 (deepest first)
    awk -v p="$1/" 'index($2, p) == 1 { print $2 }' /proc/self/mounts | sort -r | while read -r m; do
        "${SUDO[@]}" umount -l "$m" 2>/dev/null || true
    done
}

SUDO=()
if [ "$(id -u)" != 0 ]; then SUDO=(sudo); fi

build_base() {
    if [ ${#SUDO[@]} -gt 0 ] && ! have sudo; then
        die "making $BASE with debootstrap needs root or sudo (or set HAA_BASE_IMAGE=python:3.11-slim where a registry is reachable)"
    fi
    have debootstrap || die "debootstrap is missing; run scripts/docker-setup.sh (make docker-setup)"
    local mirror tmp t0
    mirror=$(debian_mirror || true)
    tmp=$(mktemp -d /var/tmp/haa-base.XXXXXX)
    # shellcheck disable=SC2064
    trap "umount_under '$tmp'; ${SUDO[*]} rm -rf --one-file-system '$tmp'" EXIT
    say "making base image $BASE: debootstrap --variant=minbase $SUITE (+ $BASE_PACKAGES) ${mirror:-<debootstrap default mirror>}"
    t0=$(now)
    if ! "${SUDO[@]}" debootstrap --variant=minbase --include="$BASE_PACKAGES" "$SUITE" "$tmp/root" ${mirror:+"$mirror"} \
        >"$tmp/debootstrap.log" 2>&1; then
        tail -n 20 "$tmp/debootstrap.log" >&2
        [ -f "$tmp/root/debootstrap/debootstrap.log" ] && tail -n 20 "$tmp/root/debootstrap/debootstrap.log" >&2
        die "debootstrap failed (see above)"
    fi
    umount_under "$tmp/root"
    # Slim it: package caches and lists, docs, man pages, translations.
    "${SUDO[@]}" rm -rf "$tmp/root"/var/cache/apt/archives/*.deb "$tmp/root"/var/cache/apt/*.bin "$tmp/root"/var/lib/apt/lists/* \
        "$tmp/root"/usr/share/doc/* "$tmp/root"/usr/share/man/* "$tmp/root"/usr/share/info/* \
        "$tmp/root"/usr/share/locale/* "$tmp/root"/var/log/*.log "$tmp/root"/debootstrap
    "${SUDO[@]}" tar --numeric-owner -C "$tmp/root" -c . | docker import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["/bin/bash"]' \
        --message "debootstrap --variant=minbase $SUITE + $BASE_PACKAGES (scripts/build-image.sh)" \
        - "$BASE" >/dev/null
    umount_under "$tmp"
    "${SUDO[@]}" rm -rf --one-file-system "$tmp"
    trap - EXIT
    say "base image $BASE made in $(since "$t0") s ($(docker image inspect -f '{{.Size}}' "$BASE" | awk '{ printf "%.0f MB", $1 / 1e6 }'))"
}

if [ "${HAA_REBUILD_BASE:-0}" != 1 ] && docker image inspect "$BASE" >/dev/null 2>&1; then
    say "base image $BASE present (HAA_REBUILD_BASE=1 rebuilds it)"
elif [[ "$BASE" == haa-base:* ]]; then
    build_base
else
    say "base image $BASE not present: pulling it"
    docker pull "$BASE" || die "cannot pull $BASE (no registry here?); unset HAA_BASE_IMAGE to make haa-base:$SUITE offline"
fi

# ---------------------------------------------------------------- 2. wheelhouse
T_WH=$(now)
mkdir -p "$WHEELHOUSE"
"$PYTHON" -m pip --version >/dev/null 2>&1 || die "no pip for $PYTHON (set PYTHON=/path/to/python3.11)"
PIP=("$PYTHON" -m pip --disable-pip-version-check)
src=$(mktemp -d /tmp/haa-src.XXXXXX)
trap 'rm -rf "$src"' EXIT
# Build from a copy of the working tree (tracked and untracked-but-not-ignored files), so that the build
# leaves nothing in the checkout and a stale build/ dir cannot slip deleted modules into the wheel.
if git -C "$ROOT" rev-parse --is-inside-work-tree >/dev/null 2>&1; then
    git -C "$ROOT" ls-files -z --cached --others --exclude-standard |
        (cd "$ROOT" && while IFS= read -r -d '' f; do [ -f "$f" ] && printf '%s\0' "$f"; done) |
        tar -C "$ROOT" --null -T - -c | tar -C "$src" -x
else
    tar -C "$ROOT" --exclude=./.venv --exclude=./compose/wheelhouse --exclude=./build -c . | tar -C "$src" -x
fi
rm -f "$WHEELHOUSE"/haa-*.whl
"${PIP[@]}" wheel --no-deps --wheel-dir "$WHEELHOUSE" "$src" >/tmp/haa-pip-wheel.log 2>&1 || {
    tail -n 20 /tmp/haa-pip-wheel.log >&2
    die "pip wheel of the project failed (log: /tmp/haa-pip-wheel.log)"
}
rm -rf "$src"
trap - EXIT
HAA_WHEEL=$(ls "$WHEELHOUSE"/haa-*.whl)
# Target: the image's interpreter (CPython 3.11, glibc 2.36 in bookworm), whatever the host is.
TARGET=(--only-binary=:all: --implementation cp --python-version 3.11 --abi cp311
    --platform manylinux_2_36_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64
    --platform manylinux2014_x86_64 --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64)
PIPLOG=/tmp/haa-pip.log
if "${PIP[@]}" download --no-index --find-links "$WHEELHOUSE" --dest "$WHEELHOUSE" "${TARGET[@]}" \
    "$HAA_WHEEL" >"$PIPLOG" 2>&1; then
    say "wheelhouse already holds every runtime dependency (no download)"
else
    say "pip download: runtime dependencies of $(basename "$HAA_WHEEL") for cp311 manylinux x86_64"
    "${PIP[@]}" download --dest "$WHEELHOUSE" "${TARGET[@]}" "$HAA_WHEEL" >"$PIPLOG" 2>&1 || {
        grep -v 'is ignored: it is neither a file nor a directory' "$PIPLOG" | tail -n 15 >&2
        die "pip download of the runtime dependencies failed (the host needs its package index for this step; log: $PIPLOG)"
    }
fi
say "wheelhouse: $(find "$WHEELHOUSE" -name '*.whl' | wc -l) wheels, $(du -sh "$WHEELHOUSE" | cut -f1) ($(since "$T_WH") s)"

# ---------------------------------------------------------------- 3. token
if [ -d "$TOKEN" ]; then
    # `docker compose up` before the first build makes an empty directory at a missing bind-mount source.
    rmdir "$TOKEN" 2>/dev/null || die "$TOKEN is a directory; remove it"
fi
if [ ! -s "$TOKEN" ]; then
    (umask 077 && od -An -N32 -tx1 /dev/urandom | tr -d ' \n' >"$TOKEN" && echo >>"$TOKEN")
    say "generated the cluster token $TOKEN"
fi
for d in $(grep -o '\./tls/hosts/[A-Za-z0-9_.-]*' "$CTX/compose.yaml" | sort -u); do
    (umask 077 && mkdir -p "$CTX/$d")
done

# ---------------------------------------------------------------- 4. image
T_IMG=$(now)
build=(docker build --network none --build-arg "BASE_IMAGE=$BASE" -t "$IMAGE" -f "$CTX/Dockerfile"
    --label io.haa.image=haa-hostd
    --label "org.opencontainers.image.revision=$(git -C "$ROOT" rev-parse --short HEAD 2>/dev/null || echo unknown)"
    --label "org.opencontainers.image.version=$(basename "$HAA_WHEEL" | cut -d- -f2)")
# Without buildx the client falls back to the legacy builder (and says so); keep that notice out of the way.
docker buildx version >/dev/null 2>&1 || export DOCKER_BUILDKIT=0
say "docker build --network none -t $IMAGE (base $BASE)"
"${build[@]}" "$CTX" >/tmp/haa-image-build.log 2>&1 || {
    tail -n 30 /tmp/haa-image-build.log >&2
    die "docker build failed (full log: /tmp/haa-image-build.log)"
}
# Drop what this build left dangling: the build stage (kept by the legacy builder; rarely reusable, the haa
# wheel changes every time) and the previous haa-hostd image, unless a container still uses it.
docker image prune --force --filter label=io.haa.stage=build >/dev/null 2>&1 || true
docker image prune --force --filter label=io.haa.image=haa-hostd >/dev/null 2>&1 || true
say "image $IMAGE built in $(since "$T_IMG") s, $(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{ printf "%.0f MB", $1 / 1e6 }'); total $(since "$T_ALL") s"
