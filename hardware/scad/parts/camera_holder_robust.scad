// KIWI printed part: the robust camera cage joining the robot flange adapter and a tool.
// Print: front plate's contact face on the bed. Render: openscad -o camera_holder_robust.stl camera_holder_robust.scad
include <../params.scad>
include <../lib.scad>
include <../holders.scad>
print_matrix = rot_x(180);
printed("camera_holder_robust") holder_robust();
