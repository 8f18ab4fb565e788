// Render only (not printed): camera, light holder and parallel-jaw gripper at a gap (mm,
// -D gap=...), the camera's top up.
include <../params.scad>
include <../lib.scad>
include <../holders.scad>
include <../tools.scad>
print_matrix = identity4;
gap = 40;
rotate([-90, 0, 0]) {
    color("dimgray") translate(-q_in_front) camera_body();
    color("steelblue") holder_light();
    pj_assembly(gap);
}
