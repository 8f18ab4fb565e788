// KIWI printed part: the light camera holder (handheld and worn).
// Print: plate contact face on the bed. Render: openscad -o camera_holder_light.stl camera_holder_light.scad
include <../params.scad>
include <../lib.scad>
include <../holders.scad>
print_matrix = rot_x(180);
printed("camera_holder_light") holder_light();
