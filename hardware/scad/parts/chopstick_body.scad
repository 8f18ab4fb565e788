// KIWI printed part: the chopstick unibody (clamp, hinge housing, tag plate, grip).
// Print: on its side (the clamp's side wall on the bed), with supports. Render: openscad -o chopstick_body.stl chopstick_body.scad
include <../params.scad>
include <../lib.scad>
include <../chopstick.scad>
print_matrix = rot_y(90);
printed("chopstick_body") chop_body();
