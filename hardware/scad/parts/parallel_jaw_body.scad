// KIWI printed part: the parallel-jaw body (clamp, rod end blocks, tag plate).
// Print: clamp's front face on the bed, with supports. Render: openscad -o parallel_jaw_body.stl parallel_jaw_body.scad
include <../params.scad>
include <../lib.scad>
include <../tools.scad>
print_matrix = rot_x(180);
printed("parallel_jaw_body") pj_body();
