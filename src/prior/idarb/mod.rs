//! The IDArb network (ICLR 2025) ported to candle.
