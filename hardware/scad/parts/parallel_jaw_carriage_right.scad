// KIWI printed part: the right parallel-jaw carriage with its dotted finger plate.
// Print: gripping face on the bed. Render: openscad -o parallel_jaw_carriage_right.stl parallel_jaw_carriage_right.scad
include <../params.scad>
include <../lib.scad>
include <../tools.scad>
print_matrix = rot_y(-90);
printed("parallel_jaw_carriage_right") pj_carriage(1);
