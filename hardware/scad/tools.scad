// KIWI tools other than the chopstick: the ALOHA-style parallel-jaw gripper (body with two steel
// guide rods, two carriages with dotted finger plates), the wrist cuff, the hat mount for a
// GO 3 and its ArUco tag, and the ISO 9409-1-50-4-M6 robot flange adapter.

// ---------------------------------------------------------------- parallel jaw
// Hinge frame (lib.scad): the rods run along x below the jaws' centre plane, the finger plates
// lie in it, dotted face up (+z, towards the camera). A carriage is modelled at zero gap: its
// gripping face at x = 0, the right one (side +1) reaching towards +x.
// The carriages' sweep stays in front of the tag plate (y > -tag_behind_hinge + tag_side / 2)
// and above the clamp's top edge.
pj_carriage_z = [-9.5, -1];
pj_rod_z = (pj_carriage_z[0] + pj_carriage_z[1]) / 2;
pj_carriage_y = [-pj_rod_spacing / 2 - 4.5, pj_rod_spacing / 2 + 4.5];
pj_thumb = 4;
pj_end_x = pj_max_gap / 2 + pj_carriage_length + pj_thumb;
pj_beam_y = [pj_carriage_y[0] - 16, pj_carriage_y[0] - 2];
pj_reach = pj_jaw_offset + pj_jaw_length;

module pj_carriage_right() {
    difference() {
        union() {
            translate([0, pj_carriage_y[0], pj_carriage_z[0]]) cube([pj_carriage_length, pj_carriage_y[1] - pj_carriage_y[0], pj_carriage_z[1] - pj_carriage_z[0]]);
            // Neck up to the plate.
            translate([0, pj_carriage_y[1] - 6, pj_carriage_z[0]]) cube([pj_grip_face + 6, pj_jaw_offset + 4 - pj_carriage_y[1] + 6, pj_plate / 2 - pj_carriage_z[0]]);
            // Dotted plate.
            translate([0, pj_jaw_offset, -pj_plate / 2]) cube([pj_grip_face + 6, pj_jaw_length, pj_plate]);
            // Gripping pad behind the plate.
            translate([0, pj_jaw_offset + 6, -pj_plate / 2 - pj_finger_height]) cube([5, pj_jaw_length - 8, pj_finger_height + eps]);
            // Thumb rest on the outer side of the carriage.
            translate([pj_carriage_length - eps, -4, pj_carriage_z[0]]) cube([pj_thumb, 12, pj_carriage_z[1] - pj_carriage_z[0]]);
        }
        for (y = [-1, 1] * pj_rod_spacing / 2) translate([pj_carriage_length / 2, y, pj_rod_z]) rotate([0, 90, 0])
            cylinder(d = pj_rod_d + 2 * sliding_clearance, h = 2 * pj_carriage_length + 20, center = true);
        translate([pj_grip_face, 0, pj_plate / 2]) dot_recesses(pj_dots);
    }
}

module pj_carriage(side) {
    if (side > 0) pj_carriage_right(); else mirror([1, 0, 0]) pj_carriage_right();
}

module pj_body() {
    difference() {
        union() {
            qr_clamp_block();
            in_hinge_frame() {
                // End blocks holding the rods, and the beam behind the carriages joining them.
                for (s = [-1, 1]) translate([s > 0 ? pj_end_x : -pj_end_x - 12, pj_beam_y[0], pj_carriage_z[0]])
                    cube([12, pj_carriage_y[1] - pj_beam_y[0], pj_carriage_z[1] - pj_carriage_z[0]]);
                translate([-pj_end_x - 12, pj_beam_y[0], pj_carriage_z[0]]) cube([2 * pj_end_x + 24, pj_beam_y[1] - pj_beam_y[0], tag_plate / 2 - pj_carriage_z[0]]);
                tag_plate();
            }
            hull() {
                translate([-16, -qr_length / 2, qr_clamp_back]) cube([32, 10, qr_clamp_front - qr_clamp_back]);
                in_hinge_frame() translate([-16, pj_beam_y[0], pj_carriage_z[0]]) cube([32, pj_beam_y[1] - pj_beam_y[0], 1]);
            }
        }
        qr_clamp_cut();
        in_hinge_frame() for (y = [-1, 1] * pj_rod_spacing / 2) translate([0, y, pj_rod_z]) rotate([0, 90, 0])
            cylinder(d = pj_rod_d, h = pj_rod_length + 0.5, center = true);
        camera_keepout();
    }
    qr_clamp_report(identity4);
}

module pj_assembly(gap) {
    color("lightgrey") pj_body();
    in_hinge_frame() {
        for (s = [-1, 1]) color("white") translate([s * gap / 2, 0, 0]) pj_carriage(s);
        for (y = [-1, 1] * pj_rod_spacing / 2) color("silver") translate([0, y, pj_rod_z]) rotate([0, 90, 0])
            cylinder(d = pj_rod_d, h = pj_rod_length, center = true);
    }
}

// ---------------------------------------------------------------- wrist cuff
// Q frame: the clamp, a tag plate behind the reference point (as on the grippers), and a saddle
// on the back of the wrist in front of the camera, with two strap slots.
cuff_axis_y = qr_length / 2 + 8 + cuff_saddle_thickness + cuff_wrist_radius;
module cuff_saddle() {
    r0 = cuff_wrist_radius;
    r1 = r0 + cuff_saddle_thickness;
    difference() {
        translate([0, cuff_axis_y, 1]) rotate([0, 0, -90 - cuff_saddle_arc / 2])
            rotate_extrude(angle = cuff_saddle_arc) translate([r0, 0]) square([cuff_saddle_thickness, cuff_saddle_length]);
        for (s = [-1, 1]) translate([0, cuff_axis_y, 1 + cuff_saddle_length / 2]) rotate([0, 0, -90 + s * (cuff_saddle_arc / 2 - 12)])
            translate([r0 - 1, -2, -cuff_strap_width / 2]) cube([cuff_saddle_thickness + 2, 4, cuff_strap_width]);
    }
}
module cuff() {
    difference() {
        union() {
            qr_clamp_block();
            cuff_saddle();
            // Block joining the clamp's bottom end to the saddle, in front of the channel.
            translate([-16, qr_length / 2 - 10, sliding_clearance + 0.5]) cube([32, 10 + 8 + cuff_saddle_thickness + 2, 20]);
            in_hinge_frame() {
                tag_plate();
                translate([-14, -tag_behind_hinge - 6, -10]) cube([28, 12, 10 + tag_plate / 2]);
            }
            hull() {
                translate([-14, -qr_length / 2, qr_clamp_back]) cube([28, 8, qr_clamp_front - qr_clamp_back]);
                in_hinge_frame() translate([-14, -tag_behind_hinge - 6, -10]) cube([28, 12, 1]);
            }
        }
        qr_clamp_cut();
        camera_keepout();
    }
    qr_clamp_report(identity4);
}

// ---------------------------------------------------------------- hat mount
// GO 3 lens frame (x right, y down, z forward; origin at the lens centre on the capsule's front
// face): a pocket for the capsule open at the bottom and the back, a window for the lens, an arm
// up and forward to the tag plate (the tag's printed face, centre hat_tag_above above and
// hat_tag_ahead ahead of the lens, facing forward), and strap slots for the hat.
go3_min = [-go3_width / 2 - camera_clearance, -go3_lens_below_top - camera_clearance, -go3_depth - camera_clearance];
go3_size = [go3_width + 2 * camera_clearance, go3_height + 2 * camera_clearance, go3_depth + 2 * camera_clearance];
hat_wall = 2.5;
hat_tag_side = hat_tag_size + 2 * hat_tag_quiet_zone;
module hat_mount() {
    difference() {
        union() {
            // Pocket shell.
            translate(go3_min - [hat_wall, hat_wall, 0]) cube([go3_size[0] + 2 * hat_wall, go3_size[1] * 0.7, go3_size[2] + hat_wall]);
            // Back plate against the hat, with strap slots.
            translate([-hat_strap_width / 2 - 10, go3_min[1] - hat_wall, go3_min[2] - 4]) cube([hat_strap_width + 20, go3_size[1] * 0.7, 4]);
            // Arm from the pocket's top to the tag plate.
            translate([-10, -hat_tag_above + hat_tag_side / 2 - 6, go3_min[2] - 4]) cube([20, 6, hat_tag_ahead - go3_min[2] + 4 - hat_plate + eps]);
            translate([-10, -hat_tag_above + hat_tag_side / 2 - 6, go3_min[2] - 4]) cube([20, hat_tag_above - hat_tag_side / 2 + 6 + go3_min[1] + eps, 6]);
            // Tag plate: the printed tag is glued on its front face (z = hat_tag_ahead).
            translate([-hat_tag_side / 2, -hat_tag_above - hat_tag_side / 2, hat_tag_ahead - hat_plate]) cube([hat_tag_side, hat_tag_side, hat_plate]);
        }
        translate(go3_min) cube(go3_size + [0, 0, 10]);
        // Lens window.
        translate([0, 0, -1]) cylinder(d = 20, h = hat_wall + 10);
        for (s = [-1, 1]) translate([s * (hat_strap_width / 2 + 5) - 1.5, go3_min[1], go3_min[2] - 6]) cube([3, hat_strap_width, 10]);
    }
}

// ---------------------------------------------------------------- robot flange adapter
// Flange frame: the adapter's face against the robot at z = 0, its centring spigot towards -z,
// the clamp on the other side (its Q frame: x along the flange's y, y along the flange's x, z
// towards the robot, contact face centre at z = clamp_z), turned so that the screw heads
// stay reachable beside it.
flange_standoff = 16;
flange_clamp_z = flange_disc_h + flange_standoff + qr_clamp_front;
flange_from_q = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, flange_clamp_z], [0, 0, 0, 1]];
module flange_adapter() {
    difference() {
        union() {
            cylinder(d = flange_disc_d, h = flange_disc_h);
            translate([0, 0, -flange_centring_depth]) cylinder(d = flange_centring_d - 2 * sliding_clearance, h = flange_centring_depth + eps);
            // Standoff: a box the size of the clamp.
            translate([-qr_length / 2, -qr_clamp_half_width, flange_disc_h - eps]) cube([qr_length, 2 * qr_clamp_half_width, flange_standoff + 2 * eps]);
            multmatrix(flange_from_q) qr_clamp_block();
        }
        multmatrix(flange_from_q) qr_clamp_cut();
        // Screws (counterbored from the clamp side) and the dowel hole.
        for (k = [0:flange_screws - 1]) rotate(k * 360 / flange_screws) translate([flange_pcd / 2, 0, 0]) {
            hole(flange_screw_d, 3 * flange_disc_h);
            translate([0, 0, flange_disc_h - flange_head_h]) cylinder(d = flange_head_d + 1, h = 100);
        }
        rotate(flange_dowel_angle) translate([flange_pcd / 2, 0, -flange_centring_depth - 1]) cylinder(d = flange_dowel_d, h = flange_disc_h * 0.6 + flange_centring_depth + 1);
        // Window through the standoff for a ball-end hex key to the locking screw.
        translate([0, 0, flange_disc_h + flange_standoff / 2]) cube([14, 2 * qr_clamp_half_width + 2, flange_standoff - 4], center = true);
    }
    echo(str("KIWI_QR clamp ", print_matrix * flange_from_q));
}
