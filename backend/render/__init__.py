"""The only package of the service that calls the engine (`scenesort.kernels`): camera
renders, BVHs by content hash with the skip rules, frames and frame bundles (in one process
or on Ray), scenes from files, a job's film."""
