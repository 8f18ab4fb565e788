// KIWI hardware: modules shared by every part. Include after params.scad:
//   include <../params.scad>
//   include <../lib.scad>
// A part is modelled in its own frame (the quick-release frame Q for holders and tools: the
// front-lens camera frame's axes, x right, y down, z forward, origin at the centre of the
// dovetail plate's contact face) and placed for printing by `printed(name)`, which applies the
// part's `print_matrix` (set at the top of each part file) and reports it.

eps = 0.01;

// ---------------------------------------------------------------- small helpers
function rot_x(a) = [[1, 0, 0, 0], [0, cos(a), -sin(a), 0], [0, sin(a), cos(a), 0], [0, 0, 0, 1]];
function rot_y(a) = [[cos(a), 0, sin(a), 0], [0, 1, 0, 0], [-sin(a), 0, cos(a), 0], [0, 0, 0, 1]];
function rot_z(a) = [[cos(a), -sin(a), 0, 0], [sin(a), cos(a), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
function translation(v) = [[1, 0, 0, v[0]], [0, 1, 0, v[1]], [0, 0, 1, v[2]], [0, 0, 0, 1]];
identity4 = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];

// A clearance hole for a screw or axle of diameter d along z, centred.
module hole(d, h) { cylinder(d = d + hole_allowance, h = h, center = true); }

// A hexagonal nut pocket (across flats af) along z, centred.
module nut_pocket(af, h) { cylinder(d = af / cos(30) + hole_allowance, h = h, center = true, $fn = 6); }

// The part as printed: its print_matrix applied, and a line the render test reads.
module printed(name) {
    echo(str("KIWI_PART ", name, " ", print_matrix));
    multmatrix(print_matrix) children();
}

// ---------------------------------------------------------------- quick-release
// The plate (on holders): the dovetail profile extruded along the slide axis y, with the tapped
// hole for the positioning stop screw in its contact face. Q frame.
module qr_plate() {
    difference() {
        rotate([90, 0, 0]) linear_extrude(height = qr_length, center = true) polygon(qr_plate_profile);
        translate([0, -qr_stop_from_center, -4]) cylinder(d = qr_stop_screw_d * 0.85, h = 8 + eps, center = true);
    }
}

// Place a plate at part_from_q and report its frame in the printed STL's coordinates.
module qr_plate_at(part_from_q) {
    echo(str("KIWI_QR plate ", print_matrix * part_from_q));
    multmatrix(part_from_q) qr_plate();
}

// Outer block of a clamp (on tools), Q frame: side walls, lips, floor.
qr_clamp_half_width = qr_width / 2 + sliding_clearance + qr_clamp_side_wall;
qr_clamp_back = -(qr_thickness - qr_clamp_lip_gap);
qr_clamp_front = sliding_clearance + qr_clamp_floor;
module qr_clamp_block() {
    translate([-qr_clamp_half_width, -qr_length / 2, qr_clamp_back])
        cube([2 * qr_clamp_half_width, qr_length, qr_clamp_front - qr_clamp_back]);
}

// What a clamp removes, Q frame: the channel (open at both ends), the stop slot in the floor
// (closed at the top end, where the stop screw's head comes to rest with the plate centred on
// Q), the locking screw's hole and the nut pocket behind the floor.
module qr_clamp_cut() {
    rotate([90, 0, 0]) linear_extrude(height = qr_length + 2, center = true) polygon(qr_channel_profile);
    slot_w = qr_stop_head_d + 2 * sliding_clearance;
    slot_top = -qr_stop_from_center - qr_stop_head_d / 2;
    translate([-slot_w / 2, slot_top, 0])
        cube([slot_w, qr_length, sliding_clearance + qr_stop_head_h + 0.3]);
    translate([0, 0, qr_clamp_front / 2]) hole(qr_lock_screw_d, 2 * qr_clamp_front + 2);
    translate([0, 0, sliding_clearance + qr_lock_nut_h / 2 - eps]) nut_pocket(qr_lock_nut_af, qr_lock_nut_h + 0.3);
}

// Report a clamp at part_from_q (the part unions qr_clamp_block and subtracts qr_clamp_cut there).
module qr_clamp_report(part_from_q) {
    echo(str("KIWI_QR clamp ", print_matrix * part_from_q));
}

// ---------------------------------------------------------------- tool frames
// Children in the hinge frame (origin at the hinge, x the camera's x, y along the closed jaws,
// z towards the camera: the dotted faces face +z), placed in Q.
module in_hinge_frame() { multmatrix(q_from_hinge) children(); }

// The body tag plate, hinge frame: centred tag_behind_hinge behind the hinge, in the jaws' centre
// plane; the printed tag (black square tag_size, quiet zone around it) is glued on its +z face.
tag_side = tag_size + 2 * tag_quiet_zone;
module tag_plate() {
    translate([0, -tag_behind_hinge, 0]) cube([tag_side, tag_side, tag_plate], center = true);
}

// A row of dot recesses on a face at z = 0 (into -z), along y at the given positions.
module dot_recesses(positions) {
    for (p = positions) translate([0, p, -dot_recess]) cylinder(r = dot_radius, h = dot_recess + 1);
}

// ---------------------------------------------------------------- gears
// Involute spur teeth (module m, pitch radius r, pressure angle pa) from angle a0 to a1 (deg) of
// a gear centred at the origin, as 2-D polygons (one per tooth). The tooth at angle a0 + k*360/z.
function inv(a) = tan(a) - a * PI / 180;
module gear_teeth(m, r, pa, a0, a1) {
    z = 2 * r / m;
    rb = r * cos(pa);
    ra = r + m;
    rf = r - 1.25 * m;
    // Half-angle of a tooth at the base circle (deg), less a backlash of 0.1 mm at the pitch
    // circle; below the base circle the flanks run radially.
    half = 90 / z + inv(pa) * 180 / PI - 0.05 / r * 180 / PI;
    steps = 6;
    flank = [for (i = [0:steps]) let(rr = rb + (ra - rb) * i / steps,
        al = acos(rb / rr)) [rr, half - inv(al) * 180 / PI]];
    pitch_angle = 360 / z;
    for (k = [0:floor((a1 - a0) / pitch_angle)]) rotate(a0 + k * pitch_angle)
        polygon(concat([[rf * cos(-half), rf * sin(-half)]],
            [for (p = flank) [p[0] * cos(-p[1]), p[0] * sin(-p[1])]],
            [for (i = [steps:-1:0]) let(p = flank[i]) [p[0] * cos(p[1]), p[0] * sin(p[1])]],
            [[rf * cos(half), rf * sin(half)]]));
}

// A straight rack along y (module m, pressure angle pa), pitch line at x = 0, teeth towards +x,
// body towards -x (depth behind the root), from y0 to y1, a tooth gap centred at y = 0.
module rack_teeth(m, pa, y0, y1, depth) {
    p = PI * m;
    add = m;
    ded = 1.25 * m;
    t = tan(pa);
    translate([-ded - depth, y0]) square([depth + 0.05, y1 - y0]);
    for (k = [floor(y0 / p):ceil(y1 / p)]) let(c = (k + 0.5) * p)
        if (c - p / 2 >= y0 && c + p / 2 <= y1)
            polygon([[-ded - 0.05, c - p / 4 - ded * t], [add, c - p / 4 + add * t],
                [add, c + p / 4 - add * t], [-ded - 0.05, c + p / 4 + ded * t]]);
}

// ---------------------------------------------------------------- camera (for assemblies only)
module rounded_box(size, r) {
    hull() for (x = [r, size[0] - r], y = [r, size[1] - r]) translate([x, y, 0]) cylinder(r = r, h = size[2]);
}

// The camera body in the front-lens frame (x right, y down, z forward): flat body and both lens
// bulges.
module camera_body() {
    translate([-cam_width / 2, cam_top_y, cam_mid_z - cam_flat_depth / 2])
        rounded_box([cam_width, cam_height, cam_flat_depth], cam_corner_radius);
    for (s = [-1, 1]) translate([0, 0, cam_mid_z + s * cam_flat_depth / 2]) scale([1, 1, s])
        cylinder(d1 = cam_lens_diameter, d2 = cam_lens_diameter * 0.6, h = cam_depth / 2 - cam_flat_depth / 2);
}

// What a tool must stay clear of, in Q: the camera body and its holder's front wall, grown by
// 1 mm (the plate itself is inside the clamp).
module camera_keepout() {
    translate(-q_in_front) {
        translate([-cam_width / 2 - 4, cam_top_y - 10, cam_mid_z - cam_depth])
            cube([cam_width + 8, cam_height + 30, cam_depth + cam_flat_depth / 2 + 1 + camera_clearance]);
    }
    translate([-qr_width / 2 - 6, -qr_length / 2 - 4, -qr_thickness - qr_holder_wall - 1])
        cube([qr_width + 12, cam_height, qr_holder_wall + 1 + eps]);
}
