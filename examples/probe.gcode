; Home (Z on the probe), then measure with the probe on probe_mcu.
; Run: cadence print examples/probe.gcode --config examples/simulated-probe.cfg
G28
G1 X100 Y100 Z5 F3000
QUERY_PROBE
PROBE
G1 Z5 F600
PROBE SAMPLES=3
G1 Z5 F600
PROBE_ACCURACY SAMPLES=3
G1 Z10 F600
