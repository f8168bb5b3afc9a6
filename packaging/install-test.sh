#!/usr/bin/env bash
# Follow README "Running on a board" in a clean Debian root filesystem booted by systemd under
# systemd-nspawn, and check that the service's `armbridge status` answers a member of the
# operators' group, first with no flight controller, then with the simulator as one.
#
#   sudo nice -n 19 packaging/install-test.sh ROOTFS
#
# ROOTFS is a directory for the base system (made by debootstrap on the first run, ~300 MB,
# reused afterwards). Every run boots a throw-away copy of it (`systemd-nspawn --ephemeral`), so
# each install starts from a clean system and leaves the base untouched. The container has its
# own /tmp, /run and PID 1; nothing of the host's /, /tmp or /run is bound into it. The checkout
# is bound read-only at /src. It shares the host's network (pip needs PyPI), so the simulator
# listens on the host's 127.0.0.1:14550, the example config's `udpout:127.0.0.1:14550`.
#
# Needs root, debootstrap and systemd-nspawn (Debian: debootstrap systemd-container), PyPI and a
# Debian mirror. Takes minutes; not part of the test suite. Exit 0 only if every step of the
# README's block was taken (as written, or with the reason it could not be), `armbridge status`
# answered the operator alice with no flight controller (link waiting, autopilot none yet) and
# with the simulator (link up), bob (not an operator) was refused, and signing worked both ways
# the README gives (a start, a signed goto and a reload each).
#
# Environment: SUITE (bookworm), MIRROR (http://deb.debian.org/debian), PIP_CERT (a CA bundle
# for pip inside the container, where a proxy re-signs TLS; copied in as /etc/pip.conf's cert).
set -euo pipefail

SUITE=${SUITE:-bookworm}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
MACHINE=armbridge-install-test
# What a stock Debian or Raspberry Pi OS has (procps: /bin/kill, the unit's ExecReload=), and
# not python3-venv, which the README's first step installs.
PACKAGES=systemd,systemd-sysv,dbus,python3,ca-certificates,sudo,procps
CT_PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
# Inside the container (its own root filesystem): where the checkout's tracked files are copied
# from the read-only bind at /src, as a user's clone would be.
CT_CHECKOUT=/root/armbridge

if [[ $# -ne 1 || $1 != /* || $1 == / ]]; then
    echo "usage: $0 ROOTFS   (an absolute path for the base system, not /)" >&2
    exit 2
fi
ROOTFS=${1%/}
CHECKOUT=$(cd "$(dirname "$0")/.." && pwd)
[[ $(id -u) -eq 0 ]] || { echo "$0: needs root (debootstrap, systemd-nspawn)" >&2; exit 2; }
for tool in debootstrap systemd-nspawn nsenter git python3; do
    command -v "$tool" >/dev/null || { echo "$0: $tool not found" >&2; exit 2; }
done

T0=$(date +%s)
say() { printf '\n== %s\n' "$*"; }
note() { printf '   (%s)\n' "$*"; }

# -- How nspawn runs here -------------------------------------------------------------------
# On a host booted with systemd, nspawn registers with machined and gets its own scope. On a
# host without systemd as PID 1 (a VM or container whose init is something else), it must be
# told --register=no --keep-unit, and then it splits its *current* cgroup into payload/ and
# supervisor/: so it first moves into a cgroup of its own, removed at the end.
NSPAWN_FLAGS=(--quiet)
OWN_CGROUPS=()
if [[ ! -d /run/systemd/system ]]; then
    NSPAWN_FLAGS+=(--register=no --keep-unit)
    if [[ -d /sys/fs/cgroup/unified ]]; then  # hybrid: cgroup v2 beside v1's name=systemd
        OWN_CGROUPS=(/sys/fs/cgroup/unified/"$MACHINE" /sys/fs/cgroup/systemd/"$MACHINE")
    else
        OWN_CGROUPS=(/sys/fs/cgroup/"$MACHINE")
    fi
fi
nspawn() {  # nspawn ARGS...: exec systemd-nspawn in our own cgroup(s); call in a subshell
    for cg in "${OWN_CGROUPS[@]}"; do mkdir -p "$cg" && echo "$BASHPID" >"$cg/cgroup.procs"; done
    exec systemd-nspawn "${NSPAWN_FLAGS[@]}" "$@"
}

NSPAWN_PID=
CLEAN_FILES=()
cleanup() {
    local rc=$?
    if [[ -n $NSPAWN_PID ]] && kill -0 "$NSPAWN_PID" 2>/dev/null; then
        say "Stopping the container (pid $NSPAWN_PID)"
        kill -TERM "$NSPAWN_PID"  # nspawn asks the container's systemd to power off
        # then removes its copy of the file system, which takes a while under nice
        for _ in $(seq 240); do kill -0 "$NSPAWN_PID" 2>/dev/null || break; sleep 0.5; done
        if kill -0 "$NSPAWN_PID" 2>/dev/null; then
            echo "   not down after 120 s: SIGKILL (remove the copy left beside $ROOTFS)"
            kill -KILL "$NSPAWN_PID"
        fi
        wait "$NSPAWN_PID" 2>/dev/null || true
    fi
    rm -f "${CLEAN_FILES[@]}"
    for cg in "${OWN_CGROUPS[@]}"; do
        [[ -d $cg ]] && find "$cg" -depth -type d -exec rmdir {} + 2>/dev/null || true
    done
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# -- The base system ------------------------------------------------------------------------
if [[ ! -f $ROOTFS/etc/debian_version ]]; then
    say "No base system in $ROOTFS: debootstrap $SUITE (minbase + $PACKAGES)"
    debootstrap --variant=minbase --include="$PACKAGES" "$SUITE" "$ROOTFS" "$MIRROR"
else
    say "Reusing the base system in $ROOTFS (Debian $(cat "$ROOTFS/etc/debian_version"))"
    missing=()
    for p in ${PACKAGES//,/ }; do
        chroot "$ROOTFS" dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'ok installed' ||
            missing+=("$p")
    done
    if [[ ${#missing[@]} -gt 0 ]]; then
        say "Adding to the base system: ${missing[*]}"
        (nspawn -D "$ROOTFS" --setenv=DEBIAN_FRONTEND=noninteractive \
            sh -c "apt-get update -q && apt-get install -y -q ${missing[*]}")
    fi
fi

# A Debian installer names the host and writes /etc/hosts; debootstrap does neither (it copies
# this host's /etc/hostname), and sudo then warns that it cannot resolve the host name.
if [[ ! -f $ROOTFS/etc/hosts ]]; then
    echo "$MACHINE" >"$ROOTFS/etc/hostname"
    printf '127.0.0.1\tlocalhost\n127.0.1.1\t%s\n::1\tlocalhost ip6-localhost ip6-loopback\n' \
        "$MACHINE" >"$ROOTFS/etc/hosts"
fi

# -- Boot a throw-away copy -----------------------------------------------------------------
say "Booting a throw-away copy of $ROOTFS under systemd-nspawn (checkout read-only at /src)"
BOOT_LOG=$(mktemp --tmpdir armbridge-install-test.XXXXXX.log)
CLEAN_FILES+=("$BOOT_LOG")
(nspawn --ephemeral --boot --directory="$ROOTFS" --machine="$MACHINE" --console=passive \
    --bind-ro="$CHECKOUT:/src" >"$BOOT_LOG" 2>&1) &
NSPAWN_PID=$!  # the subshell execs nspawn: this is nspawn's pid
LEADER=
for _ in $(seq 240); do
    kill -0 "$NSPAWN_PID" 2>/dev/null || { cat "$BOOT_LOG"; echo "nspawn exited" >&2; exit 1; }
    LEADER=$(cat /proc/"$NSPAWN_PID"/task/*/children 2>/dev/null | awk '{print $1; exit}')
    [[ -n $LEADER ]] && [[ $(cat /proc/"$LEADER"/comm 2>/dev/null) == systemd ]] && break
    LEADER=
    sleep 0.5
done
[[ -n $LEADER ]] || { cat "$BOOT_LOG"; echo "the container's systemd never started" >&2; exit 1; }

ct() {  # ct CMD...: run as root inside the container, with a clean environment
    nsenter --target "$LEADER" --all -- env -i PATH="$CT_PATH" HOME=/root LANG=C.UTF-8 \
        TERM=dumb "$@"
}
ct_sh() { ct /bin/bash -c "set -eo pipefail; cd $CT_CHECKOUT 2>/dev/null || cd /; $1"; }
as_user() {  # as_user USER CMD: a login shell, so the user's groups are read afresh
    ct runuser --login "$1" --command "$2"
}

for _ in $(seq 120); do ct test -S /run/systemd/private && break; sleep 0.5; done
state=$(ct systemctl is-system-running --wait || true)
SYSTEMD_VERSION=$(ct systemctl --version | head -n 1)
echo "   $SYSTEMD_VERSION in Debian $(ct cat /etc/debian_version): $state"
[[ $state == running ]] || ct systemctl --failed --no-pager || true

if [[ -n ${PIP_CERT:-} ]]; then
    say "Not a README step: pip trusts \$PIP_CERT inside the container (this network re-signs TLS)"
    ct_sh "cat > /etc/ssl/install-test-ca.pem" <"$PIP_CERT"
    ct_sh "printf '[global]\ncert = /etc/ssl/install-test-ca.pem\n' > /etc/pip.conf"
fi

say "Not a README step: the checkout, a copy of /src's tracked files in $CT_CHECKOUT"
note "pip builds in the source tree (armbridge.egg-info), so it cannot install from read-only /src"
git -C "$CHECKOUT" ls-files -z |
    ct_sh "mkdir $CT_CHECKOUT && tar -C /src --null -T - -cf - | tar -C $CT_CHECKOUT -xf -"

say "Not a README step: the operator alice exists (and bob, who is not an operator)"
ct_sh "useradd --create-home --shell /bin/bash alice && useradd --create-home --shell /bin/bash bob"

# -- README "Running on a board", line by line ----------------------------------------------
# The README's steps: its "Running on a board" code block, continuation lines joined and the
# comments dropped. Each step below is checked against it, and every one of them must be taken,
# so a README edit that this script does not follow fails the run.
README_STEPS=$(awk '/^### Running on a board/ {f = 1} f && /^```sh/ {c = 1; next} c && /^```/ {exit} c' \
    "$CHECKOUT/README.md" | sed -e ':a' -e '/\\$/N; s/\\\n *//; ta' |
    sed -E 's/[[:space:]]{2,}#.*$//; s/[[:space:]]+$//')
TAKEN=()
readme() {  # readme "README step" ["what is run instead, and why"]: say it (and check it)
    printf '\n$ %s\n' "$1"
    if [[ $# -gt 1 ]]; then note "$2"; fi
    if grep -qxF -- "$1" <<<"$README_STEPS"; then
        TAKEN+=("$1")
    else
        echo "FAIL: not a step of README's \"Running on a board\" (edited there?): $1" >&2
        exit 1
    fi
}
run_readme() {  # run_readme "README step": run it as written, as root, in the checkout
    readme "$1"
    ct_sh "$1"
}
step() {  # step "command": a command beyond the README, said and run as root
    printf '\n$ %s\n' "$1"
    ct_sh "$1"
}

run_readme "sudo apt-get update && sudo apt-get install -y python3-venv"
run_readme "sudo groupadd --system armbridge"
run_readme "sudo usermod -aG armbridge alice"
run_readme "sudo /usr/bin/python3 -m venv /opt/armbridge/.venv"
readme "sudo /opt/armbridge/.venv/bin/pip install /path/to/this/checkout" \
    "the checkout is $CT_CHECKOUT"
t=$(date +%s)
ct_sh "sudo /opt/armbridge/.venv/bin/pip install $CT_CHECKOUT"
PIP_S=$(($(date +%s) - t))
run_readme "sudo ln -s /opt/armbridge/.venv/bin/armbridge /usr/local/bin/"
run_readme "/opt/armbridge/.venv/bin/armbridge shipped config | sudo install -D -m 644 /dev/stdin /etc/armbridge/armbridge.toml"
readme "sudoedit /etc/armbridge/armbridge.toml" \
    "skipped (interactive): the example is used as is; its link.url udpout:127.0.0.1:14550 is where the simulator will listen"
run_readme "sudo sh -c 'umask 077 && head -c 32 /dev/urandom > /etc/armbridge/signing.key'"
run_readme "sudo CREDENTIALS_DIRECTORY=/etc/armbridge /opt/armbridge/.venv/bin/armbridge check-config /etc/armbridge/armbridge.toml"
run_readme "/opt/armbridge/.venv/bin/armbridge shipped unit | sudo tee /etc/systemd/system/armbridge.service >/dev/null"
t=$(date +%s)
run_readme "sudo NUMBA_CACHE_DIR=/var/cache/armbridge /opt/armbridge/.venv/bin/python -P -m companion.ik"
COMPILE_S=$(($(date +%s) - t))
note "the kernels compiled into /var/cache/armbridge in ${COMPILE_S} s (root's files: the first start hands them to the service's user)"
t=$(date +%s)
run_readme "sudo systemctl daemon-reload && sudo systemctl enable --now armbridge" || {
    ct systemctl status --no-pager armbridge || true
    ct journalctl -u armbridge --no-pager -n 50 || true
    exit 1
}
START_S=$(($(date +%s) - t))
note "enable --now returned after ${START_S} s (READY: the kernels loaded from the cache compiled at install)"
# The first start must load what the install compiled, not compile again (seconds, not ms).
LOADED=$(ct journalctl -u armbridge --no-pager -o cat | grep -m 1 -oE 'IK kernels ready in [0-9.]+ s' || true)
echo "   daemon: ${LOADED:-no 'IK kernels ready' line}"
ct ls -ld /var/cache/armbridge /var/cache/private/armbridge
load_s=${LOADED##* in }
load_s=${load_s% s}
if [[ -z $load_s ]] || ! python3 -c "import sys; sys.exit(float('$load_s') > 5.0)"; then
    echo "FAIL: the first start did not load the install's kernels (${LOADED:-no line}): it compiled them" >&2
    exit 1
fi
readme "journalctl -u armbridge -f" "without -f, which never returns"
ct journalctl -u armbridge --no-pager -o short-monotonic

link_state() {  # the link state in alice's `armbridge status --json`, or "no answer"
    as_user alice "armbridge status --json" 2>/dev/null |
        python3 -c 'import json, sys; print(json.load(sys.stdin)["status"]["link"])' 2>/dev/null ||
        echo "no answer"
}
wait_link_up() {  # wait_link_up: up to 30 s
    local deadline=$(($(date +%s) + 30))
    link=$(link_state)
    while [[ $link != up && $(date +%s) -lt $deadline ]]; do
        sleep 0.5
        link=$(link_state)
    done
    [[ $link == up ]]
}
start_sim() {  # start_sim UNIT [SIM FLAGS...]: the simulator as a transient unit in the container
    local unit=$1
    shift
    ct systemd-run --quiet --unit="$unit" /opt/armbridge/.venv/bin/python -m sim_servo \
        --udp 127.0.0.1:14550 "$@"
}

readme "armbridge status" "as alice (README: '# as alice'), in a login shell: her new group applies"
rc=0
STATUS_1=$(as_user alice "armbridge status" 2>&1) || rc=$?
echo "$STATUS_1"
if [[ $rc -ne 0 ]] || ! grep -Eq '^link (waiting|lost) +autopilot none yet' <<<"$STATUS_1"; then
    echo "FAIL: status as alice with no flight controller: exit $rc, or not 'link waiting/lost, autopilot none yet'" >&2
    exit 1
fi

while IFS= read -r line; do
    [[ -z $line ]] && continue
    printf '%s\n' "${TAKEN[@]}" | grep -qxF -- "$line" ||
        { echo "FAIL: README step not taken by this script: $line" >&2; exit 1; }
done <<<"$README_STEPS"
note "all ${#TAKEN[@]} steps of README's \"Running on a board\" taken"

# -- Beyond the README: an outsider, the link coming up, signing -------------------------------
say "Not a README step: bob (not in armbridge) is refused"
rc=0
as_user bob "armbridge status" || rc=$?
if [[ $rc -ne 3 ]]; then
    echo "FAIL: bob, outside the operators' group: exit $rc, not 3 (daemon not reachable)" >&2
    exit 1
fi

say "Not a README step: the simulated autopilot on udp 127.0.0.1:14550 (the example's link.url)"
start_sim armbridge-sim
wait_link_up || { echo "FAIL: link $link 30 s after the simulator started" >&2; exit 1; }
printf '\n$ armbridge status                              # as alice, the simulator running\n'
as_user alice "armbridge status"
ct journalctl -u armbridge --no-pager -o short-monotonic -n 4

count_log() {  # count_log REGEX: lines of the daemon's own journal matching it (not systemd's
    # "Reloaded armbridge.service")
    ct journalctl -u armbridge _COMM=armbridge --no-pager -o cat --case-sensitive=yes \
        --grep "$1" 2>/dev/null | wc -l
}
signed_ok() {  # signed_ok GOTO_ARGS: restart, link up with the signing simulator, a goto as
    # alice, then a reload. systemd issue #24291 (252): with DynamicUser=, credentials were
    # unreadable to command lines after the first; ExecReload= is one, and a reload re-reads
    # the key, so the reload is what would fail.
    local before
    step "sudo systemctl restart armbridge" || return 1
    wait_link_up || { echo "   link: $link"; return 1; }
    printf '\n$ armbridge goto %s --wait   # as alice\n' "$1"
    as_user alice "armbridge goto $1 --wait" >/dev/null || return 1
    as_user alice "armbridge status" | head -n 2
    before=$(count_log '^INFO armbridge: reloaded ')
    step "sudo systemctl reload armbridge" || return 1
    for _ in $(seq 40); do
        [[ $(count_log '^INFO armbridge: reloaded ') -gt $before ]] && break
        sleep 0.5
    done
    ct journalctl -u armbridge --no-pager -o short-monotonic -n 3
    [[ $(count_log '^INFO armbridge: reloaded ') -gt $before && $(count_log 'reload refused') -eq 0 ]]
}

say "Not a README step: signing as README 'The signing key' says (the simulator signs too)"
SIGNING=()
step "sudo sed -i 's|^# signing_key = .*|signing_key = \"credential:signing.key\"|' /etc/armbridge/armbridge.toml"
step "sudo CREDENTIALS_DIRECTORY=/etc/armbridge /opt/armbridge/.venv/bin/armbridge check-config /etc/armbridge/armbridge.toml"
step "sudo systemctl restart armbridge"
# The key is in use: the unsigned simulator's frames are refused, and the link stays down.
refused=0
for _ in $(seq 30); do
    refused=$(as_user alice "armbridge status --json" 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)["status"]
print(s["link_counters"]["rejected_unsigned"] if s["link"] != "up" else -1)' 2>/dev/null || echo 0)
    [[ $refused -gt 0 || $refused -lt 0 ]] && break
    sleep 0.5
done
echo "   the unsigned simulator: ${refused} frames refused as unsigned (-1: link up)"
[[ $refused -gt 0 ]] || SIGNING+=("refusing the unsigned simulator: FAIL")
ct systemctl stop armbridge-sim
start_sim armbridge-sim-signed --signing-key /etc/armbridge/signing.key
if signed_ok "45 10 20 0 45 0"; then
    SIGNING+=("LoadCredential= (\"credential:signing.key\"): PASS")
else
    SIGNING+=("LoadCredential= (\"credential:signing.key\"): FAIL")
    ct journalctl -u armbridge --no-pager -o short-monotonic -n 12 || true
fi

say "Not a README step: signing the README's other way (the key in a group of its own)"
ct systemctl reset-failed armbridge 2>/dev/null || true
step "sudo groupadd --system armbridge-key && sudo chgrp armbridge-key /etc/armbridge/signing.key && sudo chmod 0640 /etc/armbridge/signing.key"
printf '\n$ sudo systemctl edit armbridge   # LoadCredential= (empty), SupplementaryGroups=dialout armbridge-key\n'
note "interactive: the drop-in it would write, written directly"
ct_sh "mkdir -p /etc/systemd/system/armbridge.service.d && printf '[Service]\nLoadCredential=\nSupplementaryGroups=dialout armbridge-key\n' > /etc/systemd/system/armbridge.service.d/override.conf && systemctl daemon-reload"
step "sudo sed -i 's|^signing_key = .*|signing_key = \"/etc/armbridge/signing.key\"|' /etc/armbridge/armbridge.toml"
if signed_ok "45 10 20 0 45 0"; then
    SIGNING+=("the key's own group (armbridge-key): PASS")
else
    SIGNING+=("the key's own group (armbridge-key): FAIL")
    ct journalctl -u armbridge --no-pager -o short-monotonic -n 12 || true
fi

say "Summary"
echo "   $SYSTEMD_VERSION (Debian $SUITE, systemd-nspawn --boot); pip install ${PIP_S} s, kernel compile ${COMPILE_S} s, enable --now ${START_S} s (${LOADED}), whole run $(($(date +%s) - T0)) s"
echo "   status as alice: answered with no flight controller and with the simulator (link up); bob refused"
for way in "${SIGNING[@]}"; do echo "   signing, $way"; done
if [[ ${SIGNING[*]} == *FAIL* ]]; then
    echo "   FAIL"
    exit 1
fi
echo "   PASS"
