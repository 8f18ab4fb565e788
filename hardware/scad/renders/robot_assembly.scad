// Render only (not printed): robot flange adapter, robust holder with the camera, chopstick
// gripper below it, the camera's top up.
include <../params.scad>
include <../lib.scad>
include <../holders.scad>
include <../chopstick.scad>
include <../tools.scad>
print_matrix = identity4;
rotate([-90, 0, 0]) {
    color("dimgray") translate(-q_in_front) camera_body();
    color("steelblue") holder_robust();
    chop_assembly(20);
    // The adapter's clamp on the holder's top plate: q_from_qtop * qtop_from_flange.
    color("darkorange") multmatrix(q_from_qtop * [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, flange_clamp_z], [0, 0, 0, 1]]) flange_adapter();
}
