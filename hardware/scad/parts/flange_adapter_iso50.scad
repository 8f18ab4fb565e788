// KIWI printed part: the ISO 9409-1-50-4-M6 robot flange adapter.
// Print: robot face up, clamp's back on the bed. Render: openscad -o flange_adapter_iso50.stl flange_adapter_iso50.scad
include <../params.scad>
include <../lib.scad>
include <../tools.scad>
print_matrix = rot_x(180);
printed("flange_adapter_iso50") flange_adapter();
