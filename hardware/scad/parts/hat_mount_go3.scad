// KIWI printed part: the hat mount for an Insta360 GO 3 and the head ArUco tag.
// Print: tag plate's face on the bed. Render: openscad -o hat_mount_go3.stl hat_mount_go3.scad
include <../params.scad>
include <../lib.scad>
include <../tools.scad>
print_matrix = rot_x(180);
printed("hat_mount_go3") hat_mount();
