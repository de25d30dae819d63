"""The papers' own GPU figures (GTX 580), as printed, for the tables that compare against them.

2012 paper (Vinkler et al.), Tables 6.1 (spatial median) and 6.2 (binned SAH): per scene its
triangle count, build ms at leaf sizes 8/16/32 and MRays/s of primary, AO (7 per primary
ray) and random rays at those leaf sizes, 1024x1024. Table 6.3: task-pool DACRT MRays/s,
spatial median and RDH, primary/AO/random at 512 and 1024. 2013 paper (Ravichandran and
Narayanan): Table 1, ms per 1024x1024 frame of primary rays (structure included); Table 2,
shadow, specular and AO (8 per hit) ms; Table 3, peak memory MB. Only the scenes the shared
folder also has are kept; the papers' Dragon, Buddha and Blade/Turbine are the full scans
(871k, 1,087k, 1,765k triangles), ours are decimated (100k, 100k, 199k).
"""

from __future__ import annotations

LEAVES = (8, 16, 32)
# scene: (triangles, build ms, primary, ao, random), each per leaf size 8/16/32
BVH_MEDIAN = {
    "conference": (283_000, (34.2, 24.2, 17.5), (87.1, 80.6, 59.3), (69.8, 59.6, 37.7),
                   (41.6, 33.3, 22.2)),
    "sponza": (76_000, (12.9, 9.0, 6.4), (83.2, 72.7, 54.6), (38.2, 28.6, 17.4),
               (32.6, 23.8, 14.4)),
    "sibenik": (80_000, (14.3, 11.9, 11.7), (61.9, 56.9, 41.8), (40.1, 31.2, 19.3),
                (61.4, 46.9, 31.4)),
    "buddha": (1_087_000, (135.0, 75.2, 49.9), (216.5, 161.8, 109.7), (243.6, 185.1, 121.9),
               (30.4, 22.2, 14.1)),
    "dragon": (871_000, (104.0, 55.8, 39.4), (187.8, 139.2, 94.4), (175.6, 136.0, 90.4),
               (32.5, 23.9, 15.2)),
    "blade": (1_765_000, (207.1, 120.4, 77.8), (207.8, 157.9, 106.6), (340.6, 275.0, 190.8),
              (37.8, 28.1, 17.9)),
}
BVH_SAH = {
    "conference": (283_000, (51.2, 41.1, 37.4), (143.4, 133.2, 91.4), (98.6, 84.1, 52.1),
                   (54.6, 43.5, 27.8)),
    "sponza": (76_000, (21.8, 19.6, 19.3), (132.6, 116.4, 88.1), (64.8, 50.1, 30.4),
               (50.5, 36.5, 22.6)),
    "sibenik": (80_000, (27.4, 27.3, 26.6), (100.7, 88.9, 63.5), (59.0, 44.9, 27.9),
                (83.6, 63.1, 40.8)),
    "buddha": (1_087_000, (186.2, 143.1, 124.0), (230.0, 172.8, 117.2), (260.8, 197.3, 128.2),
               (32.5, 23.6, 14.8)),
    "dragon": (871_000, (147.3, 115.5, 100.8), (208.2, 156.4, 105.0), (189.1, 145.7, 96.4),
               (35.0, 25.5, 16.1)),
    "blade": (1_765_000, (303.4, 234.4, 205.1), (228.0, 171.0, 111.9), (358.1, 285.3, 193.4),
              (39.9, 29.8, 18.9)),
}
# scene: {(split, kind, size): MRays/s}
DACRT_POOL = {
    name: {(split, kind, size): value
           for split, row in (("median", med), ("rdh", rdh))
           for (kind, size), value in zip(
               [(k, s) for k in ("primary", "ao", "random") for s in (512, 1024)], row,
               strict=True)}
    for name, med, rdh in (
        ("conference", (0.757, 1.611, 1.671, 2.690, 0.335, 0.651),
         (1.132, 2.298, 2.198, 3.674, 0.405, 0.879)),
        ("sponza", (0.917, 1.878, 1.486, 2.103, 0.417, 0.695),
         (0.824, 2.173, 1.840, 2.596, 0.401, 0.824)),
        ("sibenik", (0.449, 0.952, 1.191, 1.789, 0.526, 0.927),
         (0.507, 1.130, 1.775, 2.596, 0.783, 1.501)),
        ("buddha", (0.688, 1.492, 0.928, 1.776, 0.074, 0.139),
         (0.988, 2.237, 1.130, 2.306, 0.081, 0.161)),
        ("dragon", (0.742, 1.614, 0.854, 1.597, 0.085, 0.155),
         (0.988, 2.250, 1.039, 2.049, 0.098, 0.191)),
        ("blade", (0.265, 0.554, 2.964, 6.764, 0.050, 0.098),
         (0.357, 0.650, 4.614, 9.341, 0.055, 0.111)),
    )
}
# 2013: scene -> {kind: ms per 1024x1024 frame}; "blade" is the papers' Turbine
BREADTH_FIRST_MS = {
    "bunny": {"primary": 87, "shadow": 67, "specular": 96, "ao": 149},
    "conference": {"primary": 148, "shadow": 197, "specular": 222, "ao": 240},
    "sponza": {"shadow": 220, "specular": 246, "ao": 280},
    "dragon": {"primary": 155, "shadow": 128, "specular": 177, "ao": 192},
    "buddha": {"primary": 165, "shadow": 150, "specular": 190, "ao": 204},
    "blade": {"primary": 223, "shadow": 213, "specular": 252, "ao": 287},
}
BREADTH_FIRST_PEAK_MB = {"bunny": 47.66, "conference": 85.82, "dragon": 96.87,
                         "buddha": 107.89}
