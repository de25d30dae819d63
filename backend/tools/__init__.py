"""Tools only a packager or a developer runs from a checkout: `scenesort addon-zip` and
`scenesort bench`, with the peer tracers (Warp's wp.Mesh, Embree) that bench and
benchmarks/ measure the engine against. The wheel bundled into the Blender extension
leaves this package out (tools/addon_zip.py strips it)."""
