//! printer.cfg parsing.
