//! The operator's head (paper §4.3.2): the hat marker seen by the wrists' rear lenses, turned
//! into scene-frame observations of the head, fused into the head's track, and the head
//! camera's poses through the head mount.

pub mod episode;
pub mod marker;
pub mod track;
