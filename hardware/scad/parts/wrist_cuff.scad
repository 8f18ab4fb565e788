// KIWI printed part: the wrist cuff (bare-hand module).
// Print: clamp's front face on the bed, with supports under the saddle. Render: openscad -o wrist_cuff.stl wrist_cuff.scad
include <../params.scad>
include <../lib.scad>
include <../tools.scad>
print_matrix = rot_x(180);
printed("wrist_cuff") cuff();
