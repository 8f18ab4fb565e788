// KIWI printed part: the chopstick unibody (clamp, hinge housing, tag plate, grip).
// Print: clamp's front face on the bed, with supports under the housing and grip. Render: openscad -o chopstick_body.stl chopstick_body.scad
include <../params.scad>
include <../lib.scad>
include <../chopstick.scad>
print_matrix = rot_x(180);
printed("chopstick_body") chop_body();
