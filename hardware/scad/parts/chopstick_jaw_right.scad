// KIWI printed part: the right chopstick jaw (hub below the brim plane).
// Print: dotted face on the bed, supports under the hub. Render: openscad -o chopstick_jaw_right.stl chopstick_jaw_right.scad
include <../params.scad>
include <../lib.scad>
include <../chopstick.scad>
print_matrix = rot_x(180);
printed("chopstick_jaw_right") chop_jaw(1);
