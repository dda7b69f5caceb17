#!/usr/bin/env bash
# Installs the Debian packages polspike needs (LLVM 19 for Mitsuba's LLVM variants,
# ffmpeg for MP4 output). Runs only as root and only when something is missing;
# otherwise prints what to install and continues (the scalar backend still works).
set -u
need=()
[ -e /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 ] || need+=(libllvm19)
command -v ffmpeg >/dev/null 2>&1 || need+=(ffmpeg)
[ ${#need[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "polspike: installing Debian packages: ${need[*]}"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null) \
    || echo "polspike: warning: could not install ${need[*]}; Mitsuba falls back to the scalar backend"
else
  echo "polspike: warning: not root; please install: ${need[*]} (Mitsuba will fall back to the scalar backend)"
fi
exit 0
