#!/usr/bin/env bash
# Idempotent: install what the job-script tests need on Debian/Ubuntu, only what is missing:
# Slurm (slurmctld + slurmd + client commands), munge (Slurm's authentication) and shellcheck
# (lints jobs/*.sh). A one-node cluster is then started by tools/slurm/cluster.sh.
set -euo pipefail
pkgs=(slurm-wlm munge shellcheck)
missing=()
for p in "${pkgs[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "[slurm-setup] apt-get install ${missing[*]}"
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
echo "[slurm-setup] ok: $(slurmd -V), munge $(dpkg-query -W -f='${Version}' munge), shellcheck $(shellcheck --version | awk '/^version:/ {print $2}')"
