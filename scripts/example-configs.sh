#!/bin/sh
# How many of Klipper's example configs load and plan: each config/printer-*.cfg and
# config/generic-*.cfg of a Klipper checkout, with only `serial:` replaced by `simulator`, gets
# `cadence print --batch` of G28 and an extruded 10 mm square (X 10..20, Y 10..20, Z 1). Prints
# one line per refused config (its error) and the count.
#
# usage: scripts/example-configs.sh KLIPPER_CHECKOUT [CADENCE_BINARY]
set -u
klipper=${1:?usage: $0 KLIPPER_CHECKOUT [CADENCE_BINARY]}
cadence=${2:-target/debug/cadence}
work=$(mktemp -d /tmp/cadence-example-configs.XXXXXX)
trap 'rm -rf "$work"' EXIT
cat > "$work/square.gcode" <<'EOF'
G28
G90
M83
G1 Z1 F600
G1 X10 Y10 F6000
G1 X20 Y10 E0.5 F1200
G1 X20 Y20 E0.5
G1 X10 Y20 E0.5
G1 X10 Y10 E0.5
EOF
ok=0
total=0
for cfg in "$klipper"/config/printer-*.cfg "$klipper"/config/generic-*.cfg; do
    total=$((total + 1))
    name=$(basename "$cfg")
    sed 's/^\([[:space:]]*serial[[:space:]]*[:=]\).*/\1 simulator/' "$cfg" > "$work/$name"
    if err=$("$cadence" print "$work/square.gcode" --config "$work/$name" --batch "$work/out.bin" 2>&1 >/dev/null); then
        ok=$((ok + 1))
    else
        printf '%s: %s\n' "$name" "$(printf '%s\n' "$err" | grep 'error' | head -n 1)"
    fi
done
echo "$ok of $total load and plan"
