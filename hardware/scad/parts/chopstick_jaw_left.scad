// KIWI printed part: the left chopstick jaw (hub in the brim plane).
// Print: dotted face on the bed. Render: openscad -o chopstick_jaw_left.stl chopstick_jaw_left.scad
include <../params.scad>
include <../lib.scad>
include <../chopstick.scad>
print_matrix = rot_x(180);
printed("chopstick_jaw_left") chop_jaw(-1);
