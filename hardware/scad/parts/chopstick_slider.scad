// KIWI printed part: the chopstick's rack slider.
// Print: flat, right rack's layer on the bed. Render: openscad -o chopstick_slider.stl chopstick_slider.scad
include <../params.scad>
include <../lib.scad>
include <../chopstick.scad>
print_matrix = identity4;
printed("chopstick_slider") chop_slider();
