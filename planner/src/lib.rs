//! Motion planning.
