// KIWI camera holders, Q frame: the light holder (a cradle for handheld and worn use) and the
// robust holder (a cage that joins the robot flange adapter above the camera to a tool below
// it). Both carry the dovetail plate on the camera's front face below the lenses and hold the
// camera with a 1/4"-20 screw into its tripod socket.

// Camera envelope (with clearance) in Q.
cam_min = [-cam_width / 2 - camera_clearance, cam_top_y - camera_clearance, cam_mid_z - cam_flat_depth / 2 - camera_clearance] - q_in_front;
cam_size = [cam_width + 2 * camera_clearance, cam_height + 2 * camera_clearance, cam_flat_depth + 2 * camera_clearance];
holder_side = 3;
holder_floor = 7;
wall_front_z = cam_min[2] + cam_size[2];
holder_x = cam_size[0] / 2 + holder_side;
floor_y = cam_min[1] + cam_size[1];
tripod_at = [0, floor_y, cam_mid_z - q_in_front[2]];

module camera_cavity() { translate(cam_min) cube(cam_size); }

// Floor with the tripod screw's hole and its head's counterbore from below.
module holder_floor() {
    difference() {
        translate([-holder_x, floor_y, cam_min[2] - holder_side]) cube([2 * holder_x, holder_floor, cam_size[2] + holder_side + qr_holder_wall]);
        translate(tripod_at) rotate([-90, 0, 0]) {
            hole(cam_tripod_screw_d, 30);
            translate([0, 0, holder_floor - cam_tripod_head_h + eps]) cylinder(d = cam_tripod_head_d + hole_allowance, h = 10);
        }
    }
}

// Front wall from the plate's top end down to the floor.
module holder_front_wall() {
    translate([-holder_x, -qr_length / 2 - 4, wall_front_z]) cube([2 * holder_x, floor_y - (-qr_length / 2 - 4) + holder_floor, qr_holder_wall + eps]);
}

module holder_light() {
    difference() {
        union() {
            qr_plate_at(identity4);
            holder_front_wall();
            holder_floor();
            // Low side walls and a back lip.
            for (s = [-1, 1]) translate([s > 0 ? cam_size[0] / 2 : -holder_x, floor_y - 30, cam_min[2] - holder_side])
                cube([holder_side, 30 + eps, cam_size[2] + holder_side + qr_holder_wall]);
            translate([-holder_x, floor_y - 14, cam_min[2] - holder_side]) cube([2 * holder_x, 14 + eps, holder_side]);
            // Lanyard loop on the back lip.
            translate([0, floor_y + holder_floor / 2, cam_min[2] - holder_side - 4]) rotate([0, 90, 0])
                difference() { cylinder(r = 5, h = 10, center = true); cylinder(r = 2.5, h = 11, center = true); }
        }
        camera_cavity();
    }
}

// The robust cage: the light holder's floor and front wall, full-height corner posts, a top
// bridge and a second plate on top for the flange adapter's clamp (its frame Q_top: x the
// camera's x, y the camera's z, z up out of its contact face).
top_bridge = 5;
top_contact_y = cam_min[1] - top_bridge - qr_thickness;
q_from_qtop = [[1, 0, 0, 0], [0, 0, -1, top_contact_y], [0, 1, 0, cam_mid_z - q_in_front[2]], [0, 0, 0, 1]];
module holder_robust() {
    post = 6;
    difference() {
        union() {
            qr_plate_at(identity4);
            holder_front_wall();
            holder_floor();
            for (s = [-1, 1], b = [0, 1]) translate([s > 0 ? cam_size[0] / 2 : -holder_x - post + holder_side,
                    cam_min[1] - top_bridge, b == 0 ? cam_min[2] - holder_side : wall_front_z - post + qr_holder_wall])
                cube([post, cam_size[1] + top_bridge + eps, post]);
            // Side rails joining the posts at the bottom and the top.
            for (s = [-1, 1], y = [cam_min[1] - top_bridge, floor_y - 12]) translate([s > 0 ? cam_size[0] / 2 : -holder_x - post + holder_side, y, cam_min[2] - holder_side])
                cube([post, y < 0 ? top_bridge + 8 : 12, cam_size[2] + holder_side + qr_holder_wall]);
            translate([-holder_x - post + holder_side, cam_min[1] - top_bridge, cam_min[2] - holder_side])
                cube([2 * (holder_x + post - holder_side), top_bridge, cam_size[2] + holder_side + qr_holder_wall]);
            qr_plate_at(q_from_qtop);
        }
        camera_cavity();
    }
}
