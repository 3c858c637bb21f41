#!/usr/bin/env bash
# Prove the Raspberry Pi path on an x86 machine: run `fcnpose-tf run` in an emulated arm64 Debian
# bookworm userland (Python 3.11, LiteRT, numpy, OpenCV, no TensorFlow) and compare its keypoints with
# the same command on the host. See docs/raspberry-pi.md, section "Checking the Pi path without a Pi".
#
# usage: sudo tools/pi_emulated_check.sh [--model MODEL.tflite] [--frames DIR] [options]
#
#   --model PATH       .tflite to run, any format the runtime takes: float16/float32, the full-integer int8
#                      file (uint8 pixel input, int8 maps), a Pi 5 float16 file (default: the bundled 70%
#                      float16 model in saved_models/); every shipped one: --model each in turn
#   --frames DIR       directory of images (default: --count synthetic UR5 frames from fcnpose_tf.data.synth)
#   --count N          how many synthetic frames to make when --frames is not given (default: 4)
#   --threads N        interpreter threads on both sides (default: 1)
#   --cpu NAME         emulated CPU, cortex-a53 (Pi 3, default), cortex-a72 (Pi 4) or cortex-a76 (Pi 5:
#                      ARMv8.2 with float16 arithmetic, which XNNPACK uses for a file exported with
#                      reduced-precision metadata)
#   --tolerance PX     max keypoint distance allowed, frame px (default: 0.5; 1.0 with --cpu cortex-a76)
#   --maps-tolerance X max abs difference of the output maps allowed, in probability (quantized maps are
#                      dequantized first; the summary also gives their difference in levels) (default: 1e-4;
#                      0.05 with --cpu cortex-a76, where a float16-native file computes in float16, so its
#                      maps and keypoints are not x86's: docs/raspberry-pi.md, section 5)
#   --maps-only        pass on the raw-map check alone (while `fcnpose-tf run` is missing)
#   --host-python PY   Python on the host with fcnpose-tf's core deps and pip, setuptools, wheel
#                      (default: $VIRTUAL_ENV's, else ./.venv's, else fcnpose-tf's on PATH, else python3)
#   --cache DIR        where the rootfs and wheels are kept
#                      (default: ${FCNPOSE_PI_CACHE:-$HOME/.cache/fcnpose-tf/pi-rootfs})
#   --rebuild          build the rootfs and its venv again
#   --direct           don't use binfmt_misc: call qemu-aarch64-static explicitly
#   --keep-work        keep the work directory (frames, models, outputs) and print its path
#
# Needs root (debootstrap, chroot, mounts in a private mount namespace) and, on the first run, Debian's
# and PyPI's package registries (apt-get installs debootstrap and qemu-user-static when missing).
# The first run builds and caches the rootfs (a few minutes); later runs reuse it. Emulated invokes take
# about a second each: the timings printed here are no speed figure for a Pi.
# Environment: FCNPOSE_PI_CACHE (cache dir), FCNPOSE_PI_MIRROR (Debian mirror for debootstrap).
set -Eeuo pipefail

PROG=pi_emulated_check
GUEST_WORK=/mnt/fcnpose-work
GUEST_WHEELS=/mnt/fcnpose-wheels
GUEST_VENV=/opt/fcnpose-venv
GUEST_PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin

# ---------------------------------------------------------------------------------------------------
# Guest mode: `pi_emulated_check.sh __guest ROOTFS WORK WHEELS CPUINFO QEMU_CPU MODE -- CMD...`, always
# started through `unshare --mount --propagation private`, so every mount here dies with this process
# and none is seen by the host. Mounts /proc (with a fake ARM /proc/cpuinfo), /sys, /dev, the work and
# wheel directories, runs CMD chrooted, and unmounts on the way out.
# ---------------------------------------------------------------------------------------------------
if [[ ${1:-} == __guest ]]; then
    shift
    rootfs=$1 work=$2 wheels=$3 cpuinfo=$4 qemu_cpu=$5 mode=$6
    shift 6
    [[ ${1:-} == -- ]] && shift
    mounted=()
    guest_cleanup() {
        local i
        for ((i = ${#mounted[@]} - 1; i >= 0; i--)); do
            umount "${mounted[i]}" 2>/dev/null || umount -l "${mounted[i]}" 2>/dev/null || true
        done
    }
    trap guest_cleanup EXIT
    guest_fail() { echo "[$PROG guest] error: $*" >&2; exit 2; }
    check_no_symlink() {  # never mount onto a symlink (debootstrap may leave proc/sys pointing at the host's)
        local path=$rootfs part parts
        IFS=/ read -ra parts <<<"${1#/}"
        for part in "${parts[@]}"; do
            path=$path/$part
            [[ -L $path ]] && guest_fail "$path is a symlink; refusing to mount onto it (run again with --rebuild)"
        done
        return 0
    }
    mount_at() {  # mount_at dir|file TARGET-IN-ROOTFS mount-args...
        local kind=$1 target=$rootfs$2
        shift 2
        check_no_symlink "${target#"$rootfs"}"
        if [[ $kind == file ]]; then [[ -e $target ]] || touch "$target"; else mkdir -p "$target"; fi
        mount "$@" "$target" || guest_fail "mount $* $target failed"
        mounted+=("$target")
    }
    mount_at dir /proc -t proc proc
    mount_at file /proc/cpuinfo --bind "$cpuinfo"
    mount_at dir /sys -t sysfs sysfs
    mount_at dir /dev --bind /dev
    mount_at dir "$GUEST_WORK" --bind "$work"
    mount_at dir "$GUEST_WHEELS" --bind "$wheels"
    mount -o remount,bind,ro "$rootfs$GUEST_WHEELS" 2>/dev/null || true
    envs=(PATH="$GUEST_PATH" HOME=/root LANG=C.UTF-8 QEMU_CPU="$qemu_cpu" PYTHONDONTWRITEBYTECODE=1
          PYTHONUNBUFFERED=1 PIP_CONFIG_FILE=/dev/null PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1
          TMPDIR=/tmp)
    case $mode in
        binfmt|native) env -i "${envs[@]}" chroot "$rootfs" "$@" & ;;
        direct) env -i "${envs[@]}" chroot "$rootfs" /usr/bin/qemu-aarch64-static -cpu "$qemu_cpu" "$@" & ;;
        *) guest_fail "unknown mode $mode" ;;
    esac
    child=$!
    # Run in the background and wait, so that a TERM/INT reaches this shell at once and is passed on;
    # the EXIT trap then unmounts after the child has gone.
    trap 'kill -TERM "$child" 2>/dev/null' TERM INT HUP
    status=0
    wait "$child" || status=$?
    while kill -0 "$child" 2>/dev/null; do wait "$child" || status=$?; done
    exit "$status"
fi

# ---------------------------------------------------------------------------------------------------
# Host mode
# ---------------------------------------------------------------------------------------------------
SCRIPT=$(readlink -f "${BASH_SOURCE[0]}")
TOOLS_DIR=$(dirname "$SCRIPT")
REPO=$(dirname "$TOOLS_DIR")
HELPER=$TOOLS_DIR/pi_emulated/pi_check.py

MODEL='' FRAMES='' COUNT=4 THREADS=1 CPU=cortex-a53 TOLERANCE='' MAPS_TOLERANCE='' MAPS_ONLY=0 HOST_PY=''
CACHE=${FCNPOSE_PI_CACHE:-$HOME/.cache/fcnpose-tf/pi-rootfs} REBUILD=0 DIRECT=0 KEEP_WORK=0
MIRROR=${FCNPOSE_PI_MIRROR:-http://deb.debian.org/debian}

usage() { sed -n '2,/^set -E/p' "$SCRIPT" | sed '$d' | sed 's/^# \{0,1\}//'; }
need_value() { [[ $# -ge 2 && -n $2 ]] || { echo "error: $1 needs a value (see --help)" >&2; exit 2; }; }
while [[ $# -gt 0 ]]; do
    case $1 in
        --model) need_value "$@"; MODEL=$2; shift 2 ;;
        --frames) need_value "$@"; FRAMES=$2; shift 2 ;;
        --count) need_value "$@"; COUNT=$2; shift 2 ;;
        --threads) need_value "$@"; THREADS=$2; shift 2 ;;
        --cpu) need_value "$@"; CPU=$2; shift 2 ;;
        --tolerance) need_value "$@"; TOLERANCE=$2; shift 2 ;;
        --maps-tolerance) need_value "$@"; MAPS_TOLERANCE=$2; shift 2 ;;
        --maps-only) MAPS_ONLY=1; shift ;;
        --host-python) need_value "$@"; HOST_PY=$2; shift 2 ;;
        --cache) need_value "$@"; CACHE=$2; shift 2 ;;
        --rebuild) REBUILD=1; shift ;;
        --direct) DIRECT=1; shift ;;
        --keep-work) KEEP_WORK=1; shift ;;
        -h|--help) usage; exit 0 ;;
        *) echo "error: unknown argument '$1' (see --help)" >&2; exit 2 ;;
    esac
done

STEP="arguments"
STEP_ACTIVE=0
STEP_T0=$SECONDS
T0=$SECONDS
WORK=
TIMINGS=()
log() { printf '[%s %s] %s\n' "$PROG" "$(date +%H:%M:%S)" "$*"; }
fail() {
    trap - ERR
    printf '[%s] error: %s\n' "$PROG" "$*" >&2
    echo "FAIL: $STEP: $*"
    exit 1
}
on_err() {
    local status=$? line=$1
    trap - ERR
    echo "FAIL: $STEP: a command failed (exit status $status, $SCRIPT line $line); see the messages above"
    exit 1
}
trap 'on_err $LINENO' ERR
on_exit() {
    if [[ -n $WORK && -d $WORK ]]; then
        if [[ $KEEP_WORK == 1 ]]; then log "work directory kept: $WORK"; else rm -rf --one-file-system -- "$WORK"; fi
    fi
}
trap on_exit EXIT
on_signal() {
    trap - ERR INT TERM
    if [[ -n ${CHILD_PID:-} ]]; then
        kill -TERM "$CHILD_PID" 2>/dev/null || true
        wait "$CHILD_PID" 2>/dev/null || true
    fi
    echo "FAIL: $STEP: interrupted"
    exit 130
}
trap on_signal INT TERM
step() {
    end_step
    STEP=$1
    STEP_ACTIVE=1
    STEP_T0=$SECONDS
    log "== $STEP"
}
end_step() {
    if [[ $STEP_ACTIVE == 1 ]]; then TIMINGS+=("$(printf '%5ds  %s' $((SECONDS - STEP_T0)) "$STEP")"); fi
    STEP_ACTIVE=0
}

[[ $THREADS =~ ^[1-9][0-9]*$ ]] || fail "--threads must be a positive integer, got '$THREADS'"
[[ $COUNT =~ ^[1-9][0-9]*$ ]] || fail "--count must be a positive integer, got '$COUNT'"
# /proc/cpuinfo as each Pi's 64-bit Raspberry Pi OS shows it (qemu's AT_HWCAP, which LiteRT's cpuinfo reads
# first, follows -cpu by itself).
PI_FEATURES="fp asimd evtstrm crc32 cpuid" PI_SOC=BCM2835
case $CPU in
    cortex-a53) CPU_PART=0xd03 CPU_REV=4 PI_MODEL="Raspberry Pi 3 Model B Rev 1.2" ;;
    cortex-a72) CPU_PART=0xd08 CPU_REV=3 PI_MODEL="Raspberry Pi 4 Model B Rev 1.4" ;;
    cortex-a76) CPU_PART=0xd0b CPU_REV=1 PI_MODEL="Raspberry Pi 5 Model B Rev 1.0" PI_SOC=BCM2712
        PI_FEATURES="fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp cpuid asimdrdm lrcpc dcpop asimddp" ;;
    *) fail "--cpu must be cortex-a53, cortex-a72 or cortex-a76, got '$CPU'" ;;
esac
# A Cortex-A76 computes a float16-native file in float16: the maps then move by float16 rounding (0.025 and
# 0.71 frame px for the bundled file's 4 synthetic frames), so the defaults there check that it runs and keeps
# its keypoints (1 frame px: ~0.35 map px at 224, inside the export gate's 1 map px), not bit-equality.
if [[ -z $MAPS_TOLERANCE ]]; then
    if [[ $CPU == cortex-a76 ]]; then MAPS_TOLERANCE=0.05; else MAPS_TOLERANCE=1e-4; fi
fi
if [[ -z $TOLERANCE ]]; then
    if [[ $CPU == cortex-a76 ]]; then TOLERANCE=1.0; else TOLERANCE=0.5; fi
fi
if [[ -z $MODEL ]]; then
    MODEL=$(ls "$REPO"/saved_models/*70*.tflite 2>/dev/null | head -1 || true)
    [[ -n $MODEL ]] || fail "no bundled 70% model (saved_models/*70*.tflite) yet; pass --model MODEL.tflite"
fi
[[ -f $MODEL ]] || fail "model $MODEL does not exist"
MODEL=$(readlink -f "$MODEL")
if [[ -n $FRAMES ]]; then
    [[ -d $FRAMES ]] || fail "frames directory $FRAMES does not exist"
fi
[[ $(id -u) == 0 ]] || fail "needs root (debootstrap, chroot and mounts); run it with sudo"
[[ -f $HELPER ]] || fail "helper $HELPER is missing"

# --- host tools -------------------------------------------------------------------------------------
step "host tools"
HOST_ARCH=$(uname -m)
missing=()
command -v debootstrap >/dev/null || missing+=(debootstrap)
command -v unshare >/dev/null && command -v flock >/dev/null || missing+=(util-linux)
if [[ $HOST_ARCH != aarch64 ]]; then
    command -v qemu-aarch64-static >/dev/null || missing+=(qemu-user-static)
    command -v update-binfmts >/dev/null || missing+=(binfmt-support)
fi
if ((${#missing[@]})); then
    log "installing ${missing[*]} with apt-get"
    command -v apt-get >/dev/null || fail "missing ${missing[*]} and no apt-get to install them"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq \
        || fail "apt-get update failed (is Debian's package registry reachable?)"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null \
        || fail "apt-get install ${missing[*]} failed"
fi

if [[ -z $HOST_PY ]]; then
    if [[ -n ${VIRTUAL_ENV:-} && -x $VIRTUAL_ENV/bin/python ]]; then HOST_PY=$VIRTUAL_ENV/bin/python
    elif [[ -x $REPO/.venv/bin/python ]]; then HOST_PY=$REPO/.venv/bin/python
    elif command -v fcnpose-tf >/dev/null && head -1 "$(command -v fcnpose-tf)" | grep -q '^#!/.*python'; then
        HOST_PY=$(head -1 "$(command -v fcnpose-tf)" | sed 's/^#!//; s/ .*//')
    else HOST_PY=$(command -v python3 || true); fi
fi
if [[ -z $HOST_PY ]] || ! "$HOST_PY" -c 'import numpy, cv2' 2>/dev/null; then
    fail "host Python '${HOST_PY:-python3}' cannot import numpy and cv2; pass --host-python of a venv with fcnpose-tf[pi]"
fi
"$HOST_PY" -m pip --version >/dev/null 2>&1 || fail "host Python $HOST_PY has no pip (needed to download the aarch64 wheels)"
"$HOST_PY" -c 'import setuptools, wheel' 2>/dev/null \
    || fail "host Python $HOST_PY lacks setuptools or wheel (needed to build this package's wheel)"
log "host: $HOST_ARCH, Python $("$HOST_PY" -c 'import platform; print(platform.python_version())') ($HOST_PY)"

mkdir -p "$CACHE"
CACHE=$(readlink -f "$CACHE")
exec 9>"$CACHE/.lock"
flock -n 9 || { log "another check holds $CACHE/.lock; waiting"; flock 9; }
ROOTFS=$CACHE/rootfs
WORK=$(mktemp -d "${TMPDIR:-/tmp}/fcnpose-pi-check.XXXXXX")
chmod 755 "$WORK"
cp "$HELPER" "$WORK/pi_check.py"

# --- binfmt_misc --------------------------------------------------------------------------------------
step "arm64 emulation (binfmt_misc)"
MODE=direct
BINFMT_ENTRY=/proc/sys/fs/binfmt_misc/qemu-aarch64
if [[ $HOST_ARCH == aarch64 ]]; then
    MODE=native
elif [[ $DIRECT == 1 ]]; then
    log "--direct: qemu-aarch64-static is called explicitly (child processes inside cannot start)"
else
    if [[ ! -e /proc/sys/fs/binfmt_misc/status ]]; then
        log "mounting binfmt_misc on /proc/sys/fs/binfmt_misc"
        mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc 2>/dev/null \
            || log "could not mount binfmt_misc; falling back to calling qemu-aarch64-static directly"
    fi
    if [[ -e /proc/sys/fs/binfmt_misc/status && ! -e $BINFMT_ENTRY ]]; then
        log "registering qemu-aarch64 with binfmt_misc"
        update-binfmts --enable qemu-aarch64 >/dev/null 2>&1 || true
        if [[ ! -e $BINFMT_ENTRY ]]; then
            printf '%s' ':qemu-aarch64:M::\x7fELF\x02\x01\x01\x00\x00\x00\x00\x00\x00\x00\x00\x00\x02\x00\xb7\x00:\xff\xff\xff\xff\xff\xff\xff\x00\xff\xff\xff\xff\xff\xff\xff\xff\xfe\xff\xff\xff:/usr/bin/qemu-aarch64-static:F' \
                >/proc/sys/fs/binfmt_misc/register 2>/dev/null || true
        fi
    fi
    if [[ -e $BINFMT_ENTRY ]] && head -1 "$BINFMT_ENTRY" | grep -q '^enabled'; then
        MODE=binfmt
    else
        log "qemu-aarch64 is not usable through binfmt_misc; calling qemu-aarch64-static directly"
    fi
fi
log "mode: $MODE"

# guest CMD...: run CMD in the arm64 rootfs (private mount namespace, fake ARM cpuinfo, nice 10).
CPUINFO=$WORK/cpuinfo
{
    ncpu=$(nproc)
    for ((i = 0; i < ncpu; i++)); do
        printf 'processor\t: %d\nBogoMIPS\t: 38.40\nFeatures\t: %s\n' "$i" "$PI_FEATURES"
        printf 'CPU implementer\t: 0x41\nCPU architecture: 8\nCPU variant\t: 0x0\nCPU part\t: %s\nCPU revision\t: %s\n\n' \
            "$CPU_PART" "$CPU_REV"
    done
    printf 'Hardware\t: %s\nModel\t\t: %s\n' "$PI_SOC" "$PI_MODEL"
} >"$CPUINFO"
mkdir -p "$WORK/wheels"
WHEELS=$WORK/wheels   # replaced by the cached wheel directory below
CHILD_PID=
run_child() {  # run a long command in the background and wait for it, so a TERM/INT stops it (see on_signal)
    local status=0
    "$@" &
    CHILD_PID=$!
    wait "$CHILD_PID" || status=$?
    CHILD_PID=
    return "$status"
}
guest() {
    run_child nice -n 10 unshare --mount --propagation private -- \
        bash "$SCRIPT" __guest "$ROOTFS" "$WORK" "$WHEELS" "$CPUINFO" "$CPU" "$MODE" -- "$@"
}
install_qemu_into_rootfs() {  # $1 = rootfs; the interpreter binfmt names must exist inside unless flag F is set
    [[ $MODE == native ]] && return 0
    local root=$1 interp
    install -D -m 755 "$(command -v qemu-aarch64-static)" "$root/usr/bin/qemu-aarch64-static"
    if [[ $MODE == binfmt ]] && ! grep -q '^flags:.*F' "$BINFMT_ENTRY"; then
        interp=$(sed -n 's/^interpreter //p' "$BINFMT_ENTRY")
        [[ -n $interp ]] && install -D -m 755 "$(command -v qemu-aarch64-static)" "$root$interp"
    fi
    return 0
}
mounts_under() { awk -v p="$1" '$5 == p || index($5, p "/") == 1 {print $5}' /proc/self/mountinfo; }
remove_tree() {  # remove a rootfs directory, never crossing into something mounted under it
    local dir=$1
    [[ -e $dir ]] || return 0
    [[ -z $(mounts_under "$dir") ]] || fail "something is mounted under $dir ($(mounts_under "$dir" | head -3 | tr '\n' ' ')); unmount it first"
    rm -rf --one-file-system -- "$dir"
}

# --- rootfs -------------------------------------------------------------------------------------------
step "arm64 Debian bookworm rootfs"
if [[ $REBUILD == 1 && -e $ROOTFS ]]; then
    log "--rebuild: removing the cached rootfs"
    remove_tree "$ROOTFS"
fi
if [[ -f $ROOTFS/.fcnpose-rootfs-ok ]]; then
    log "cached: $ROOTFS ($(cat "$ROOTFS/.fcnpose-rootfs-ok"))"
else
    partial=$CACHE/rootfs.partial
    remove_tree "$partial"
    remove_tree "$ROOTFS"
    log "building with debootstrap from $MIRROR (one-off, a few minutes; log: $CACHE/debootstrap.log)"
    t_build=$SECONDS
    if ! run_child nice -n 10 unshare --mount --propagation private -- \
        debootstrap --arch=arm64 --variant=minbase --include=python3,python3-venv \
        bookworm "$partial" "$MIRROR" >"$CACHE/debootstrap.log" 2>&1; then
        tail -5 "$CACHE/debootstrap.log" | sed 's/^/    /' >&2
        fail "debootstrap failed (full log: $CACHE/debootstrap.log)"
    fi
    for d in proc sys dev; do  # never mount onto a symlink that may point at the host's
        if [[ -L $partial/$d ]]; then rm -f "$partial/$d"; mkdir -p "$partial/$d"; fi
    done
    mkdir -p "$partial$GUEST_WORK" "$partial$GUEST_WHEELS"
    install_qemu_into_rootfs "$partial"
    ROOTFS_FINAL=$ROOTFS ROOTFS=$partial
    guest /usr/bin/python3 -c 'import platform, sys
assert platform.machine() == "aarch64", platform.machine()
assert sys.version_info[:2] == (3, 11), sys.version
print(f"  rootfs Python {platform.python_version()} on {platform.machine()}")' \
        || fail "the new rootfs's python3 does not run as aarch64 Python 3.11"
    ROOTFS=$ROOTFS_FINAL
    echo "Debian bookworm arm64, built $(date -u +%Y-%m-%dT%H:%MZ) in $((SECONDS - t_build)) s" >"$partial/.fcnpose-rootfs-ok"
    mv "$partial" "$ROOTFS"
    log "built in $((SECONDS - t_build)) s: $ROOTFS ($(du -sh --one-file-system "$ROOTFS" | cut -f1))"
fi
install_qemu_into_rootfs "$ROOTFS"
mkdir -p "$ROOTFS$GUEST_WORK" "$ROOTFS$GUEST_WHEELS"
if [[ $MODE == binfmt ]] && ! guest /bin/true 2>/dev/null; then
    log "binfmt_misc does not start aarch64 binaries in the rootfs; calling qemu-aarch64-static directly"
    MODE=direct
fi

# --- aarch64 wheels -------------------------------------------------------------------------------------
step "aarch64 wheels (downloaded on the host)"
# The same versions as the host's, so both sides run the same numpy, OpenCV and LiteRT.
mapfile -t REQS < <("$HOST_PY" - <<'EOF'
from importlib import metadata
for dist in ("ai-edge-litert", "numpy", "opencv-python-headless", "pip"):
    try:
        print(f"{dist}=={metadata.version(dist)}")
    except metadata.PackageNotFoundError:
        print(dist)
EOF
)
[[ " ${REQS[*]} " == *" ai-edge-litert=="* ]] \
    || log "warning: ai-edge-litert is not installed on the host; the x86 side will use another interpreter"
key=$(printf '%s\n' "${REQS[@]}" | sha256sum | cut -c1-12)
WHEELS=$CACHE/wheels/$key
if [[ -f $WHEELS/.complete ]]; then
    log "cached: $WHEELS"
else
    log "pip download ${REQS[*]} (manylinux aarch64, cp311)"
    rm -rf "$WHEELS.partial"
    mkdir -p "$WHEELS.partial"
    if ! "$HOST_PY" -m pip download --quiet --disable-pip-version-check --only-binary=:all: \
        --platform manylinux_2_28_aarch64 --platform manylinux_2_27_aarch64 \
        --platform manylinux_2_17_aarch64 --platform manylinux2014_aarch64 \
        --python-version 3.11 --implementation cp --abi cp311 --abi abi3 --abi none \
        -d "$WHEELS.partial" "${REQS[@]}" >"$WORK/pip-download.log" 2>&1; then
        grep -v '^WARNING: Location' "$WORK/pip-download.log" | tail -5 | sed 's/^/    /' >&2
        fail "pip download of the aarch64 wheels failed (is PyPI reachable? does ${REQS[*]} have cp311 aarch64 wheels?)"
    fi
    printf '%s\n' "${REQS[@]}" >"$WHEELS.partial/.complete"
    rm -rf "$WHEELS"
    mv "$WHEELS.partial" "$WHEELS"
fi
PIP_WHEEL=$(cd "$WHEELS" && ls pip-*.whl 2>/dev/null | head -1 || true)
[[ -n $PIP_WHEEL ]] || fail "no pip wheel in $WHEELS (remove it and run again)"
log "$(cd "$WHEELS" && ls -- *.whl | wc -l) wheels: $(cd "$WHEELS" && ls -- *.whl | sed 's/-cp.*\|-py.*//' | tr '\n' ' ')"

# --- this package ---------------------------------------------------------------------------------------
step "fcnpose-tf wheel (built on the host)"
mkdir -p "$WORK/src" "$WORK/dist"
for f in setup.cfg pyproject.toml README.md LICENSE setup.py; do
    [[ -f $REPO/$f ]] && cp "$REPO/$f" "$WORK/src/"
done
tar -C "$REPO" --exclude=__pycache__ --exclude='*.pyc' -cf - fcnpose_tf | tar -C "$WORK/src" -xf -
if ! (cd "$WORK/src" && "$HOST_PY" -m pip wheel --quiet --no-deps --no-build-isolation --no-index \
    -w "$WORK/dist" . >"$WORK/pip-wheel.log" 2>&1); then
    tail -5 "$WORK/pip-wheel.log" | sed 's/^/    /' >&2
    fail "building the fcnpose-tf wheel from $REPO failed"
fi
PKG_WHEEL=$(cd "$WORK/dist" && ls fcnpose_tf-*.whl | head -1)
log "built $PKG_WHEEL from $REPO (working tree as it is now)"

# --- venv inside ------------------------------------------------------------------------------------------
step "venv in the emulated userland (offline install)"
deps_id=$(cd "$WHEELS" && ls -- *.whl | sort | sha256sum | cut -c1-12)
if [[ $REBUILD == 0 && -f $ROOTFS$GUEST_VENV/.fcnpose-deps && $(cat "$ROOTFS$GUEST_VENV/.fcnpose-deps") == "$deps_id" ]]; then
    log "cached: $GUEST_VENV (dependencies $deps_id)"
else
    remove_tree "$ROOTFS$GUEST_VENV"
    log "python3 -m venv --without-pip $GUEST_VENV; pip install --no-index (emulated: about a minute)"
    guest /usr/bin/python3 -m venv --without-pip "$GUEST_VENV" || fail "creating the venv inside failed"
    guest "$GUEST_VENV/bin/python" "$GUEST_WHEELS/$PIP_WHEEL/pip" install --quiet --no-index \
        --find-links "$GUEST_WHEELS" "${REQS[@]}" || fail "offline pip install inside the emulated userland failed"
    echo "$deps_id" >"$ROOTFS$GUEST_VENV/.fcnpose-deps"
fi
cp "$WORK/dist/$PKG_WHEEL" "$WORK/"
guest "$GUEST_VENV/bin/python" -m pip install --quiet --no-index --no-deps --force-reinstall \
    "$GUEST_WORK/$PKG_WHEEL" || fail "installing $PKG_WHEEL inside failed"
guest "$GUEST_VENV/bin/python" -m pip check >"$WORK/pip-check.log" 2>&1 || {
    sed 's/^/    /' "$WORK/pip-check.log" >&2
    fail "pip check inside: fcnpose-tf's requirements are not met by the installed wheels"
}
log "guest environment:"
guest "$GUEST_VENV/bin/python" "$GUEST_WORK/pi_check.py" info --require-no-tensorflow \
    || fail "the guest venv is not a Pi-like environment (see above)"

# --- model and frames -----------------------------------------------------------------------------------
step "model and frames"
cp "$MODEL" "$WORK/model.tflite"
log "model: $MODEL ($(stat -c %s "$MODEL") bytes)"
if [[ -n $FRAMES ]]; then
    mkdir -p "$WORK/frames"
    find "$FRAMES" -maxdepth 1 -type f \( -iname '*.png' -o -iname '*.jpg' -o -iname '*.jpeg' -o -iname '*.bmp' \) \
        -exec cp -t "$WORK/frames" {} +
    [[ -n $(ls -A "$WORK/frames") ]] || fail "no .png/.jpg/.jpeg/.bmp image in $FRAMES"
    log "frames: $(ls "$WORK/frames" | wc -l) images from $FRAMES"
else
    PYTHONPATH=$WORK/src "$HOST_PY" "$HELPER" frames "$WORK/frames" --count "$COUNT" \
        || fail "could not write synthetic frames"
fi

# --- check 1: the interpreter alone -------------------------------------------------------------------
step "raw output maps, x86 vs emulated arm64"
PYTHONPATH=$WORK/src "$HOST_PY" "$HELPER" maps "$WORK/model.tflite" --frames "$WORK/frames" \
    --threads "$THREADS" --out "$WORK/maps-x86.npz" 2>"$WORK/maps-x86.err" \
    || { grep -v '^INFO' "$WORK/maps-x86.err" | tail -5 >&2; fail "the x86 run of $MODEL failed"; }
"$HOST_PY" "$HELPER" save-inputs "$WORK/maps-x86.npz" "$WORK/inputs-x86.npy"
t_maps=$SECONDS
guest "$GUEST_VENV/bin/python" "$GUEST_WORK/pi_check.py" maps "$GUEST_WORK/model.tflite" \
    --frames "$GUEST_WORK/frames" --inputs "$GUEST_WORK/inputs-x86.npy" --threads "$THREADS" \
    --out "$GUEST_WORK/maps-arm64.npz" --require-litert --require-xnnpack 2>"$WORK/maps-arm64.err" \
    || { grep -v '^INFO' "$WORK/maps-arm64.err" | tail -5 >&2; fail "the emulated arm64 run of $MODEL failed"; }
log "emulated: $(ls "$WORK/frames" | wc -l) invokes in $((SECONDS - t_maps)) s (emulation: no speed figure)"
PYTHONPATH=$WORK/src "$HOST_PY" "$HELPER" compare-maps "$WORK/maps-x86.npz" "$WORK/maps-arm64.npz" --tol "$MAPS_TOLERANCE" \
    --result "$WORK/maps-diff.txt" || fail "raw output maps differ by more than $MAPS_TOLERANCE"
MAPS_DIFF=$(cat "$WORK/maps-diff.txt")

# --- check 2: fcnpose-tf run end to end ---------------------------------------------------------------
step "fcnpose-tf run, x86 vs emulated arm64"
if ! PYTHONPATH=$WORK/src "$HOST_PY" -m fcnpose_tf run --help >/dev/null 2>&1; then
    end_step
    log "fcnpose-tf run is not in this tree yet: keypoint comparison not done"
    printf '%s\n' "${TIMINGS[@]}" | sed 's/^/    /'
    if [[ $MAPS_ONLY == 1 ]]; then
        echo "PASS (maps only): emulated arm64 ($CPU, Debian bookworm, Python 3.11) LiteRT output maps agree with x86: max abs diff $MAPS_DIFF (tolerance $MAPS_TOLERANCE); keypoints not compared (no fcnpose-tf run); total $((SECONDS - T0)) s"
        exit 0
    fi
    STEP="fcnpose-tf run"
    fail "fcnpose-tf run is missing from $REPO; maps agree (max abs diff $MAPS_DIFF) — use --maps-only to accept that alone"
fi
PYTHONPATH=$WORK/src "$HOST_PY" -m fcnpose_tf run "$WORK/model.tflite" --source "$WORK/frames" \
    --threads "$THREADS" --out "$WORK/k-x86.jsonl" >"$WORK/run-x86.log" 2>&1 \
    || { tail -8 "$WORK/run-x86.log" | sed 's/^/    /' >&2; fail "fcnpose-tf run on x86 failed (log above)"; }
t_run=$SECONDS
if [[ $MODE == direct ]]; then  # qemu called directly runs ELF files only, not the console script
    guest_cli=("$GUEST_VENV/bin/python" -m fcnpose_tf)
else
    guest_cli=("$GUEST_VENV/bin/fcnpose-tf")
fi
guest "${guest_cli[@]}" run "$GUEST_WORK/model.tflite" --source "$GUEST_WORK/frames" \
    --threads "$THREADS" --out "$GUEST_WORK/k-arm64.jsonl" >"$WORK/run-arm64.log" 2>&1 \
    || { tail -8 "$WORK/run-arm64.log" | sed 's/^/    /' >&2; fail "fcnpose-tf run in the emulated arm64 userland failed (log above)"; }
log "emulated fcnpose-tf run took $((SECONDS - t_run)) s; its summary:"
grep -v '^INFO' "$WORK/run-arm64.log" | tail -6 | sed 's/^/    /'
kp_status=0
"$HOST_PY" "$HELPER" compare-keypoints "$WORK/k-x86.jsonl" "$WORK/k-arm64.jsonl" --tol "$TOLERANCE" \
    --result "$WORK/kp-diff.txt" || kp_status=$?
[[ -f $WORK/kp-diff.txt ]] || fail "the keypoint comparison could not read the outputs (see above)"
read -r KP_DIFF KP_N KP_FRAMES <"$WORK/kp-diff.txt"
end_step
log "timings:"
printf '%s\n' "${TIMINGS[@]}" | sed 's/^/    /'
SUMMARY="emulated arm64 ($CPU, Debian bookworm, Python 3.11, LiteRT, no TensorFlow) vs x86: max keypoint diff $KP_DIFF px over $KP_N keypoints in $KP_FRAMES frames (tolerance $TOLERANCE px); raw maps max abs diff $MAPS_DIFF; total $((SECONDS - T0)) s"
if [[ $kp_status == 0 ]]; then
    echo "PASS: $SUMMARY"
else
    log "keypoints differ although the raw maps from identical inputs agree: the rest comes from the"
    log "frames' preprocessing (OpenCV's resize rounds a few pixels differently on arm64; see its diff above)"
    echo "FAIL: $SUMMARY"
    exit 1
fi
