// tinybvh's builders on a scene written by benchmarks/peer_build.py, timed in this process.
//   peer_build <vertices.f32x4> <indices.u32x3> <builder: avx | bvh8> <threaded 0|1> <builds>
// Prints one JSON line: the builder, each build's ms (the first is a warm-up, not counted by
// the caller) and the binary tree's SAH cost (traversal and intersection cost 1, as
// scenesort's BvhStats.sah_cost).
#define TINYBVH_IMPLEMENTATION
#include "tiny_bvh.h"

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

using namespace tinybvh;

static std::vector<char> slurp(const char* path) {
    FILE* f = std::fopen(path, "rb");
    if (!f) { std::perror(path); std::exit(2); }
    std::fseek(f, 0, SEEK_END);
    std::vector<char> data(std::ftell(f));
    std::fseek(f, 0, SEEK_SET);
    if (std::fread(data.data(), 1, data.size(), f) != data.size()) { std::perror(path); std::exit(2); }
    std::fclose(f);
    return data;
}

int main(int argc, char** argv) {
    if (argc != 6) { std::fprintf(stderr, "usage: %s vertices indices avx|bvh8 threaded builds\n", argv[0]); return 2; }
    const auto vdata = slurp(argv[1]);
    const auto idata = slurp(argv[2]);
    const std::string builder = argv[3];
    const bool threaded = std::atoi(argv[4]) != 0;
    const int builds = std::atoi(argv[5]);
    const auto* vertices = reinterpret_cast<const bvhvec4*>(vdata.data());
    const auto* indices = reinterpret_cast<const uint32_t*>(idata.data());
    const uint32_t prims = static_cast<uint32_t>(idata.size() / 12);
    const bvhvec4slice slice(vertices, static_cast<uint32_t>(vdata.size() / 16), sizeof(bvhvec4));
    std::printf("{\"builder\": \"%s\", \"ms\": [", builder.c_str());
    float sah = 0.0f;
    for (int r = 0; r < builds; ++r) {
        const auto t0 = std::chrono::steady_clock::now();
        if (builder == "avx") {  // the binary tree alone
            BVH bvh;
            bvh.threadedBuild = threaded;
            bvh.BuildAVX(slice, indices, prims);
            const auto t1 = std::chrono::steady_clock::now();
            sah = bvh.SAHCost();
            std::printf("%s%.3f", r ? ", " : "", std::chrono::duration<double, std::milli>(t1 - t0).count());
        } else {  // BuildAVX, then the 8-wide tree and its leaf blocks (its CPU traversal's)
            BVH8_CPU bvh;
            bvh.bvh8.bvh.threadedBuild = threaded;
            bvh.Build(slice, indices, prims);
            const auto t1 = std::chrono::steady_clock::now();
            sah = bvh.bvh8.bvh.SAHCost();
            std::printf("%s%.3f", r ? ", " : "", std::chrono::duration<double, std::milli>(t1 - t0).count());
        }
        std::fflush(stdout);
    }
    std::printf("], \"sah\": %.4f}\n", sah);
    return 0;
}
