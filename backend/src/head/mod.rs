//! The operator's head (paper §4.3.2): the hat marker seen by the wrists' rear lenses, turned
//! into scene-frame observations of the head.

pub mod marker;
pub mod track;
