// Render only (not printed): one part in the pose it is used in, the camera's top up
// (openscad -D 'part="chopstick_body"' -o part.png part.scad).
include <../params.scad>
include <../lib.scad>
include <../holders.scad>
include <../chopstick.scad>
include <../tools.scad>
print_matrix = identity4;
part = "chopstick_body";
// Camera frame (y down, z forward) to the viewer's frame (z up, y forward).
rotate([-90, 0, 0]) {
    if (part == "camera_holder_light") holder_light();
    if (part == "camera_holder_robust") holder_robust();
    if (part == "chopstick_body") chop_body();
    if (part == "chopstick_jaw_left") in_hinge_frame() rotate([0, 0, chop_closed_half_angle]) chop_jaw(-1);
    if (part == "chopstick_jaw_right") in_hinge_frame() rotate([0, 0, -chop_closed_half_angle]) chop_jaw(1);
    if (part == "chopstick_slider") in_hinge_frame() chop_slider();
    if (part == "parallel_jaw_body") pj_body();
    if (part == "parallel_jaw_carriage_left") in_hinge_frame() translate([-20, 0, 0]) pj_carriage(-1);
    if (part == "parallel_jaw_carriage_right") in_hinge_frame() translate([20, 0, 0]) pj_carriage(1);
    if (part == "wrist_cuff") cuff();
    if (part == "hat_mount_go3") hat_mount();
    if (part == "flange_adapter_iso50") rotate([90, 0, 0]) flange_adapter();
}
