#!/usr/bin/env bash
# System packages the real PsychoPy window test needs on a headless Debian 12 machine.
#
# Idempotent and quiet: installs only what is missing, as root, without prompts.
#   xvfb, xauth           virtual X display (the test starts Xvfb itself; xvfb-run needs xauth)
#   libgl1-mesa-dri ...   Mesa software OpenGL (llvmpipe) and the GLX/GLU libraries pyglet loads
#   libx*                 X extensions pyglet/PsychoPy open at window creation (gamma, input, ...)
#   xdotool               types keys and moves the pointer inside Xvfb like a participant would
#   libasound2 ...        ALSA/PortAudio/JACK shared libraries so psychopy.sound imports (CI has no
#                         sound card: the window then warns and runs without pink noise)
#   gcc-arm-none-eabi ... the device firmware (firmware/): ARM cross-compiler + newlib, QEMU to
#                         run the STM32 image, make + gcc for the host build; the conformance
#                         tests fail under CI when these are missing
#   chromium              headless browser that opens report.html (tests/test_html_report.py
#                         fails, never skips, without it)
set -euo pipefail

packages=(
    xvfb xauth xdotool
    libgl1 libopengl0 libgl1-mesa-dri libglx-mesa0 libglu1-mesa libegl1
    libxxf86vm1 libxi6 libxrandr2 libxinerama1 libxcursor1 libxext6 libxrender1 libxkbcommon0
    libfontconfig1 libfreetype6 fonts-dejavu-core
    libasound2 libportaudio2 libjack-jackd2-0 libsndfile1
    gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm make gcc
    chromium
)

missing=()
for pkg in "${packages[@]}"; do
    status=$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null || true)
    [[ "$status" == "install ok installed" ]] || missing+=("$pkg")
done

if ((${#missing[@]} == 0)); then
    exit 0
fi

if [[ $(id -u) -ne 0 ]]; then
    echo "system-deps: missing ${missing[*]}; run this script as root (apt-get install)" >&2
    exit 1
fi

echo "system-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
log=$(mktemp)
# apt's chatter only matters when it fails.
if ! { apt-get update -qq && apt-get install -y -qq --no-install-recommends "${missing[@]}"; } \
    >"$log" 2>&1; then
    cat "$log" >&2
    rm -f "$log"
    echo "system-deps: apt-get failed; see above" >&2
    exit 1
fi
rm -f "$log"
