; Cadence example: a 20 mm square with extrusion, printed on the built-in simulated printer.
; Uses absolute and relative moves, both extrusion modes and a G92 reset.
G28                 ; home (sets the configured endstop positions)
G90                 ; absolute positioning
M82                 ; absolute extrusion
G92 E0
G1 Z0.3 F600        ; first layer height
G1 X50 Y50 F6000    ; travel to the corner
G1 X70 Y50 E1.0 F1800
G1 X70 Y70 E2.0
G1 X50 Y70 E3.0
G1 X50 Y50 E4.0
G92 E0              ; reset the extruder position
G91                 ; relative moves for the second layer
M83                 ; relative extrusion
G1 Z0.3 F600
G1 X20 E1.0 F1800
G1 Y20 E1.0
G1 X-20 E1.0
G1 Y-20 E1.0
G1 E-0.8 F2400      ; retract
G90
G1 X10 Y10 Z5 F6000 ; move away
M400
