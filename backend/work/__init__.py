"""Long work off the event loop: one worker thread per device, jobs with progress,
deadlines and cancel, and the content-hash store of scenes and BVHs. No HTTP, no engine."""
