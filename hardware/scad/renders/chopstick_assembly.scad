// Render only (not printed): camera, light holder and chopstick gripper with the jaws at a
// half-angle (deg, -D half=...), the camera's top up.
include <../params.scad>
include <../lib.scad>
include <../holders.scad>
include <../chopstick.scad>
print_matrix = identity4;
half = chop_closed_half_angle;
rotate([-90, 0, 0]) {
    color("dimgray") translate(-q_in_front) camera_body();
    color("steelblue") holder_light();
    chop_assembly(half);
}
