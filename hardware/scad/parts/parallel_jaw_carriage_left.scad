// KIWI printed part: the left parallel-jaw carriage with its dotted finger plate.
// Print: gripping face on the bed. Render: openscad -o parallel_jaw_carriage_left.stl parallel_jaw_carriage_left.scad
include <../params.scad>
include <../lib.scad>
include <../tools.scad>
print_matrix = rot_y(90);
printed("parallel_jaw_carriage_left") pj_carriage(-1);
