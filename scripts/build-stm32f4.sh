#!/usr/bin/env bash
# Builds the Cadence firmware image for an STM32F405/F407 (Cortex-M4F) and prints its flash and
# RAM use against the budget of a 512 KB-flash / 128 KB-RAM part.
#
#   scripts/build-stm32f4.sh [--install] [--hardware]
#
# --install   apt-get the toolchain first: Debian's Rust 1.96 with its library source
#             (rustc-web, cargo-web, rust-web-src), lld-22 and qemu-system-arm.
# --hardware  the image for the real chip (HSI 16 MHz clock tree); default: the image for
#             QEMU's STM32F405 model (`qemu-system-arm -M netduinoplus2`), whose timers and
#             CPU run at the emulator's fixed rates.
#
# The build uses Debian's cargo/rustc (any rustup toolchain is kept off PATH), RUSTC_BOOTSTRAP=1
# for -Zbuild-std=core (no prebuilt thumbv7em-none-eabihf standard library is needed) and
# ld.lld-22 as the linker. The image path is printed last:
# firmware/boards/stm32f4/target/thumbv7em-none-eabihf/release/cadence-stm32f4[-qemu].elf
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
install=0
features=(--features qemu)
suffix=-qemu
for arg in "$@"; do
    case "$arg" in
        --install) install=1 ;;
        --hardware) features=(); suffix= ;;
        *) echo "build-stm32f4.sh: unknown option '$arg' (--install, --hardware)" >&2; exit 2 ;;
    esac
done
packages=(rustc-web cargo-web rust-web-src lld-22 qemu-system-arm)
if [ "$install" = 1 ] && ! dpkg -s "${packages[@]}" >/dev/null 2>&1; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${packages[@]}" >/dev/null
fi
for tool in /usr/bin/cargo /usr/bin/rustc ld.lld-22; do
    if ! PATH=/usr/sbin:/usr/bin:/sbin:/bin command -v "$tool" >/dev/null; then
        echo "build-stm32f4.sh: $tool missing: install ${packages[*]} (or pass --install)" >&2
        exit 1
    fi
done
if [ ! -d /usr/lib/rustlib/src/rust/library ]; then
    echo "build-stm32f4.sh: the Rust library source is missing: install rust-web-src" >&2
    exit 1
fi

board="$root/firmware/boards/stm32f4"
cd "$board"
start=$(date +%s)
env -u RUSTUP_TOOLCHAIN -u CARGO_BUILD_TARGET -u RUSTFLAGS \
    PATH=/usr/sbin:/usr/bin:/sbin:/bin RUSTC=/usr/bin/rustc RUSTDOC=/usr/bin/rustdoc \
    RUSTC_BOOTSTRAP=1 CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}" \
    CARGO_TARGET_THUMBV7EM_NONE_EABIHF_RUSTFLAGS="-D warnings" \
    /usr/bin/cargo build --release "${features[@]}"
elapsed=$(( $(date +%s) - start ))
out="$board/target/thumbv7em-none-eabihf/release"
image="$out/cadence-stm32f4$suffix.elf"
cp "$out/cadence-stm32f4" "$image"

# Flash = code, constants and the initial values of .data; RAM = .data + .bss + .uninit (the
# stack takes what is left).
flash=0
ram=0
while read -r name size; do
    size=$((16#$size))
    case "$name" in
        .vector_table | .text | .rodata) flash=$((flash + size)) ;;
        .data) flash=$((flash + size)); ram=$((ram + size)) ;;
        .bss | .uninit) ram=$((ram + size)) ;;
    esac
done < <(LC_ALL=C readelf -SW "$image" | sed -n 's/^ *\[ *[0-9]*\] //p' | awk '{ print $1, $5 }')
flash_budget=$((512 * 1024))
ram_budget=$((128 * 1024))
printf 'stm32f4 image: %s (built in %d s)\n' "$image" "$elapsed"
percent() { printf '%d.%d%%' $(($1 * 100 / $2)) $(($1 * 1000 / $2 % 10)); }
printf '  flash %7d B of %7d B (%s)\n' "$flash" "$flash_budget" "$(percent "$flash" "$flash_budget")"
printf '  RAM   %7d B of %7d B (%s static; the stack uses the rest)\n' "$ram" "$ram_budget" "$(percent "$ram" "$ram_budget")"
if [ "$flash" -gt "$flash_budget" ] || [ "$ram" -gt "$ram_budget" ]; then
    echo "build-stm32f4.sh: the image exceeds the 512 KB / 128 KB budget" >&2
    exit 1
fi
