//! Controller service: per-device MFC state answering sensor samples over Zenoh.
//!
//! Not written yet: see the service issue.
