//! Wire formats between coordinator, workers and clients (defined here, and only here).
