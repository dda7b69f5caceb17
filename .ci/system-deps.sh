#!/usr/bin/env bash
# Installs the Debian packages polspike needs: libllvm19 (Mitsuba's LLVM variants; Debian 12's
# default LLVM 15 crashes them) and ffmpeg (MP4 output). With --test also chromium (the test that
# opens the demo report headless). Installs only as root and only what is missing; otherwise it
# prints what to install and continues (Mitsuba then falls back to the scalar backend, and the
# browser test skips).
set -u
need=()
[ -e /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 ] || need+=(libllvm19)
command -v ffmpeg >/dev/null 2>&1 || need+=(ffmpeg)
if [ "${1:-}" = "--test" ]; then
  command -v chromium >/dev/null 2>&1 || need+=(chromium)
fi
[ ${#need[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "polspike: installing Debian packages: ${need[*]}"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null) \
    || echo "polspike: warning: could not install ${need[*]}; continuing (scalar Mitsuba backend / browser test skipped)"
else
  echo "polspike: warning: not root; please install: ${need[*]} (Mitsuba falls back to the scalar backend)"
fi
exit 0
