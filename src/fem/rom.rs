//! placeholder
pub struct Rom;
pub struct RomModes;
pub struct RomOptions;
pub struct RomShapeOperator;
