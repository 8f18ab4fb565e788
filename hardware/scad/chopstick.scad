// KIWI chopstick gripper: unibody (quick-release clamp, hinge housing, tag plate, angled grip),
// two jaws on one common axle, and the slider whose two racks mesh the jaws' gear sectors so
// both jaws turn by the same angle. Jaw features are modelled in the hinge frame (lib.scad:
// x the camera's x, y along the closed jaws, z towards the camera) at zero opening, where both
// dot lines lie on the y axis; the jaws touch (gripping faces together) at
// chop_closed_half_angle and open to chop_max_half_angle.

// Layers along the axle (z of the hinge frame): the left jaw's hub in the brim plane, the
// right jaw's hub below it, washers between, the housing's cheeks outside.
hub_a = [-bearing_width / 2, bearing_width / 2];
hub_b = [hub_a[0] - washer - bearing_width, hub_a[0] - washer];
cheek_c = [hub_a[1] + washer, hub_a[1] + washer + 4];
cheek_f = [hub_b[0] - washer - 4, hub_b[0] - washer];
hub_r = bearing_od / 2 + 2;
jaw_reach = chop_jaw_offset + chop_jaw_length;
gear_root = chop_gear_radius - 1.25 * chop_gear_module;
gear_tip = chop_gear_radius + chop_gear_module;
gear_pitch_angle = 360 * chop_gear_module / (2 * chop_gear_radius);
// Rack: slider-frame y range of its teeth (mesh point from zero to the widest opening, plus a
// tooth each way).
rack_y = [-PI * chop_gear_module - 0.2, -chop_slider_open + PI * chop_gear_module + 0.2];
rack_depth = 3;
slider_half_width = chop_gear_radius + 1.25 * chop_gear_module + rack_depth;
// The bridge joining the racks runs behind the lowest reach of the gear sectors.
bridge_y = [rack_y[0] - 12, rack_y[0] - 6];
slider_z = [hub_b[0], hub_a[0]];

// Inner (gripping) face line of the right jaw at zero opening: x = -grip_face * y / reach.
function inner_x(y) = -chop_grip_face * y / jaw_reach;

// The right jaw (s = +1); the left jaw is its mirror image with the hub moved to hub_a.
module jaw_plan() {
    // Brim: narrow near the root, full width from y = 30, tapered at the tip.
    polygon([[inner_x(chop_jaw_offset), chop_jaw_offset], [inner_x(jaw_reach), jaw_reach],
        [chop_brim_outer * 0.4, jaw_reach], [chop_brim_outer, jaw_reach - 25],
        [chop_brim_outer, 32], [4, 24], [4, chop_jaw_offset]]);
}
module jaw_rib_plan() {
    polygon([[inner_x(30), 30], [inner_x(jaw_reach - 4), jaw_reach - 4],
        [inner_x(jaw_reach - 4) + chop_rib_width, jaw_reach - 14],
        [inner_x(30) + chop_rib_width, 30]]);
}
module chop_jaw_right(hub) {
    difference() {
        union() {
            // Brim, dotted face at z = +brim/2.
            translate([0, 0, -chop_brim / 2]) linear_extrude(chop_brim) jaw_plan();
            // Rib behind the brim along the gripping face.
            translate([0, 0, -chop_brim / 2 - chop_rib_height]) linear_extrude(chop_rib_height + eps) jaw_rib_plan();
            // Hub, arm and gear sector in the hub's layer.
            translate([0, 0, hub[0]]) linear_extrude(hub[1] - hub[0]) {
                circle(r = hub_r);
                polygon([[inner_x(0), 0], [inner_x(chop_jaw_offset + 4), chop_jaw_offset + 4],
                    [4, chop_jaw_offset + 4], [4, 0], [hub_r, -2]]);
                // Sector web and teeth, from below the mesh point to past it by the opening.
                a0 = -gear_pitch_angle;
                a1 = chop_max_half_angle + gear_pitch_angle;
                polygon(concat([[0, 0]], [for (a = [a0:4:a1]) [gear_root * cos(a), gear_root * sin(a)] * 1.003],
                    [[gear_root * cos(a1), gear_root * sin(a1)] * 1.003]));
                gear_teeth(chop_gear_module, chop_gear_radius, chop_gear_pressure_angle,
                    a0 + 0 * gear_pitch_angle, a1);
            }
            // Riser from the hub's layer to the brim where the layers differ.
            if (hub[0] < -chop_brim / 2 - eps)
                translate([0, 0, hub[0]]) linear_extrude(chop_brim / 2 - hub[0])
                    polygon([[inner_x(hub_r + 2.5), hub_r + 2.5], [inner_x(chop_jaw_offset + 6), chop_jaw_offset + 6],
                        [4, chop_jaw_offset + 6], [4, hub_r + 2.5]]);
        }
        // Bearing seat through the hub.
        translate([0, 0, (hub[0] + hub[1]) / 2]) cylinder(d = bearing_od + bearing_seat_allowance, h = hub[1] - hub[0] + 2 * eps, center = true);
        // Dot recesses in the dotted face.
        translate([0, 0, chop_brim / 2]) dot_recesses(chop_dots);
        // Rubber-band notch is on the slider; finger notch near the tip for a better pinch.
    }
}

// A jaw at zero opening, hinge frame: side -1 (left, hub in the brim plane) or +1 (right).
module chop_jaw(side) {
    if (side > 0) chop_jaw_right(hub_b);
    else mirror([1, 0, 0]) chop_jaw_right(hub_a);
}

// The slider at zero opening, hinge frame: two racks (the left one in the left hub's layer, the
// right one in the right hub's) joined by a bridge behind the hubs, with a hook for the band.
module chop_slider() {
    // Left rack: pitch line at x = -gear_radius, teeth towards +x.
    translate([0, 0, hub_a[0]]) linear_extrude(hub_a[1] - hub_a[0])
        translate([-chop_gear_radius, 0]) rack_teeth(chop_gear_module, chop_gear_pressure_angle, rack_y[0], rack_y[1], rack_depth);
    // Right rack, mirrored.
    translate([0, 0, hub_b[0]]) linear_extrude(hub_b[1] - hub_b[0])
        mirror([1, 0]) translate([-chop_gear_radius, 0]) rack_teeth(chop_gear_module, chop_gear_pressure_angle, rack_y[0], rack_y[1], rack_depth);
    // Rack bodies back to the bridge: the right one in its layer; the left one down through the
    // washer layer beside its teeth, and behind them in the bridge's layer only (below the tag
    // plate).
    translate([slider_half_width - rack_depth, bridge_y[1] - eps, hub_b[0]]) cube([rack_depth, rack_y[1] - bridge_y[1], hub_b[1] - hub_b[0]]);
    translate([-slider_half_width, rack_y[0], hub_b[0]]) cube([rack_depth, rack_y[1] - rack_y[0], hub_a[1] - hub_b[0]]);
    translate([-slider_half_width, bridge_y[1] - eps, hub_b[0]]) cube([rack_depth, rack_y[0] - bridge_y[1] + 2 * eps, hub_b[1] - hub_b[0]]);
    // Bridge.
    difference() {
        translate([-slider_half_width, bridge_y[0], hub_b[0]]) cube([2 * slider_half_width, bridge_y[1] - bridge_y[0] + eps, hub_b[1] - hub_b[0]]);
        // Band hook: a slot the band loops through.
        translate([-2, bridge_y[0] + 1.5, hub_b[0] - 1]) cube([4, 2.5, 10]);
    }
}

// Band post behind the slider (hinge frame), where the band's other end loops.
band_post_y = bridge_y[0] + chop_slider_open - 9;

// The unibody, Q frame.
module chop_body() {
    housing_x = slider_half_width + sliding_clearance + 3.5;
    difference() {
        union() {
            qr_clamp_block();
            in_hinge_frame() {
                // Housing around the slider and hubs, top at the tag plate's face behind the axle.
                translate([-housing_x, band_post_y - 6, cheek_f[0] - 3]) cube([2 * housing_x, -band_post_y + 6 + 2, -cheek_f[0] + 3 + tag_plate / 2]);
                // Cheeks carrying the axle (camera side and far side).
                for (z = [cheek_c, [cheek_f[0] - 3, cheek_f[1]]]) hull() {
                    translate([0, 0, z[0]]) cylinder(r = 8, h = z[1] - z[0]);
                    translate([-housing_x, -4, z[0]]) cube([2 * housing_x, 1, z[1] - z[0]]);
                }
                // Walls joining the camera-side cheek to the housing outside the slider.
                for (s = [-1, 1]) translate([s > 0 ? housing_x - 3.5 : -housing_x, -4, cheek_f[0] - 3])
                    cube([3.5, 4 + 2, cheek_c[1] - cheek_f[0] + 3]);
                tag_plate();
            }
            // Web from the housing's underside to the clamp's top end.
            hull() {
                translate([-16, -qr_length / 2, qr_clamp_front - 1]) cube([32, 10, 1]);
                translate([-16, -qr_length / 2, qr_clamp_back]) cube([32, 1, qr_clamp_front - qr_clamp_back]);
                in_hinge_frame() translate([-16, band_post_y - 6, cheek_f[0] - 3]) cube([32, -band_post_y + 6 - 2, 1]);
            }
            // Angled grip below the clamp's bottom end, in front of the channel, with a palm-strap slot.
            translate([0, qr_length / 2, sliding_clearance + 0.5]) rotate([chop_grip_angle, 0, 0]) difference() {
                hull() {
                    translate([-chop_grip_width / 2, -8, 0]) cube([chop_grip_width, 8, chop_grip_depth]);
                    translate([0, chop_grip_length - chop_grip_width / 2, chop_grip_depth / 2])
                        scale([1, 1, chop_grip_depth / chop_grip_width]) sphere(d = chop_grip_width);
                }
                translate([-chop_grip_width, chop_grip_length * 0.45, chop_grip_depth - 6]) cube([2 * chop_grip_width, chop_strap_width + 2, 3]);
            }
        }
        qr_clamp_cut();
        in_hinge_frame() {
            // Slider pocket in the right hub's layer (bridge, right rack, left rack's foot), open
            // to the front, and the left rack's channel in the brim layer.
            translate([-slider_half_width - sliding_clearance, band_post_y - 4, hub_b[0] - sliding_clearance])
                cube([2 * (slider_half_width + sliding_clearance), 40 - band_post_y, hub_b[1] - hub_b[0] + 2 * sliding_clearance]);
            translate([-slider_half_width - sliding_clearance, rack_y[0] + chop_slider_open - sliding_clearance, hub_b[1]])
                cube([slider_half_width - chop_gear_radius + 1.5 + sliding_clearance, 40, hub_a[1] - hub_b[1] + sliding_clearance]);
            // Room for the jaws' hubs and sectors between the cheeks (not reaching the tag plate).
            intersection() {
                translate([0, 0, hub_b[0] - washer]) cylinder(r = gear_tip + 1, h = hub_a[1] - hub_b[0] + 2 * washer);
                translate([-50, -tag_behind_hinge + tag_side / 2 + 0.5, -50]) cube(100);
            }
            translate([-housing_x - 1, 0, hub_b[0] - washer]) cube([2 * housing_x + 2, 30, hub_a[1] - hub_b[0] + 2 * washer]);
            // Axle: M3 screw through both cheeks; head counterbore on the camera side, nut pocket on the far side.
            hole(bearing_bore, 60);
            translate([0, 0, cheek_c[1]]) cylinder(d = 5.8 + hole_allowance, h = 10);
            translate([0, 0, cheek_f[0] - 3]) nut_pocket(5.5, 2 * 2.6);
            // Band post: a 3 mm pin across the band channel.
            translate([0, band_post_y, (slider_z[0] + slider_z[1]) / 2]) rotate([0, 90, 0]) hole(3, 2 * housing_x + 2);
        }
        camera_keepout();
    }
    qr_clamp_report(identity4);
}

// Assembly at a jaw half-angle (deg), Q frame, for renders.
module chop_assembly(half) {
    color("lightgrey") chop_body();
    in_hinge_frame() {
        color("white") rotate([0, 0, half]) chop_jaw(-1);
        color("white") rotate([0, 0, -half]) chop_jaw(1);
        color("orange") translate([0, -chop_gear_radius * half * PI / 180, 0]) chop_slider();
    }
}
