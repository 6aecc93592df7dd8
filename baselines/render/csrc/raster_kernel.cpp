// Tiled alpha compositing of projected 2D Gaussians on the CPU: forward and backward.
//
// This file is compiled on first use by baselines/render/kernel.py into a plain shared library
// (no Python or torch headers) and driven through ctypes with raw pointers to contiguous
// tensors. It implements exactly the rules of the dense oracle composite_reference.py
// (DESIGN.md section 3, gsplat's rules):
//
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,    dx = pixel_x - mean_x (pixel centres at j + 0.5)
//   alpha = min(0.999, o exp(-sigma)), skipped when sigma < 0 or alpha < 1/255
//   a pixel stops BEFORE the Gaussian whose contribution would bring transmittance to <= 1e-4
//   image = sum_i f_i alpha_i T_i,  alpha_out = 1 - T_final
//
// Arithmetic mirrors the oracle so that results agree to float rounding: sigma and alpha are
// evaluated in the same operation order (the build uses -ffp-contract=off, so no FMA changes the
// rounding), and transmittance is carried in double and rounded to the scalar type where it is
// used, which is what torch.cumprod does on the CPU (it accumulates float products in double).
// The termination test therefore takes the same decision as the oracle's.
//
// Binning (rk_bin_count / rk_bin_fill): the per-tile lists of tiles.bin_gaussians, built by a
// counting sort over the visible Gaussians in stable depth order (see the section below).
//
// Work split: tiles of tile_size x tile_size pixels; each tile is processed by one thread,
// Gaussians in the outer loop (front to back), and only the pixels of the Gaussian's bounding
// box (radii from the projection, one pixel of slack per side) inside the tile in the inner
// loop. Each pixel still sees its Gaussians in the same front-to-back order, so the per-pixel
// arithmetic is identical to a pixel-major loop, while a Gaussian a few pixels wide costs only
// the pixels it can reach. A per-Gaussian sigma cutoff, ln(255 o) plus a margin, rejects pixels
// before exp() is evaluated; the exact alpha test still decides at the boundary.
//
// Backward walks each pixel's list back to front from its last contributor, recovering the
// transmittance by division (T_i = T_{i+1} / (1 - alpha_i), as 3DGS and gsplat do; in double).
//
// Determinism across thread counts: the backward pass writes one gradient slot per (tile,
// Gaussian) intersection, i.e. per entry of the tile lists. A slot is written only by the thread
// that owns the tile, summing the tile's pixels in a fixed (back-to-front, row-major) order. The
// slots are then reduced per Gaussian in increasing intersection index (= increasing tile index),
// with Gaussians partitioned across threads. Every sum therefore has a fixed order that does not
// depend on how many threads run or which thread took which tile, so 1 and 2 threads give
// bitwise identical gradients. Per-thread gradient buffers would not: their reduction order
// depends on the thread count and the dynamic tile schedule. Memory cost: (6 + C) scalars per
// intersection, a few MB for typical scenes.
//
// Threads: std::thread with an atomic tile counter (dynamic schedule, tiles vary widely in cost).
// std::thread rather than OpenMP avoids loading a second OpenMP runtime next to torch's.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <exception>
#include <functional>
#include <mutex>
#include <system_error>
#include <thread>
#include <vector>

namespace {

constexpr int kAbiVersion = 1;

template <typename scalar_t>
struct Rules {
    // Constants rounded to the scalar type, as torch does when it compares a float32 tensor
    // with a Python float.
    static constexpr scalar_t alpha_min = static_cast<scalar_t>(1.0 / 255.0);
    static constexpr scalar_t alpha_max = static_cast<scalar_t>(0.999);
    static constexpr scalar_t transmittance_min = static_cast<scalar_t>(1e-4);
};

// Margin added to the exact cutoff ln(255 o): exp() and the product with o carry relative errors
// of a few 1e-7, i.e. a few 1e-7 in sigma; 1e-3 keeps every borderline pixel for the exact test.
constexpr double kSigmaCutoffMargin = 1e-3;

struct Problem {
    const void* means2d;   // [N, 2]
    const void* conics;    // [N, 3]
    const void* opacities; // [N]
    const void* features;  // [N, C]
    const int32_t* radii;  // [N, 2]
    int64_t num_gaussians;
    int64_t channels;
    const int64_t* offsets;      // [tiles + 1]
    const int64_t* gaussian_ids; // [M]
    int64_t width;
    int64_t height;
    int64_t tile_size;
    int64_t tiles_x;
    int64_t tiles_y;
};

struct TileRect {
    int64_t x0, y0, x1, y1;  // pixel rectangle [x0, x1) x [y0, y1)
    int64_t width() const { return x1 - x0; }
    int64_t pixels() const { return (x1 - x0) * (y1 - y0); }
};

TileRect tile_rect(const Problem& p, int64_t tile) {
    const int64_t tx = tile % p.tiles_x;
    const int64_t ty = tile / p.tiles_x;
    TileRect r;
    r.x0 = tx * p.tile_size;
    r.y0 = ty * p.tile_size;
    r.x1 = std::min(r.x0 + p.tile_size, p.width);
    r.y1 = std::min(r.y0 + p.tile_size, p.height);
    return r;
}

// One Gaussian's screen-space parameters, prepared once per pass (not once per tile).
template <typename scalar_t>
struct Splat {
    scalar_t mx, my, a, b, c, o;
    double sigma_cutoff;
    double col_lo, col_hi, row_lo, row_hi;  // pixel columns / rows it can reach (unclipped)
    const scalar_t* feature;
};

template <typename scalar_t>
Splat<scalar_t> prepare_splat(const Problem& p, int64_t g) {
    const scalar_t* m = static_cast<const scalar_t*>(p.means2d) + 2 * g;
    const scalar_t* q = static_cast<const scalar_t*>(p.conics) + 3 * g;
    Splat<scalar_t> s;
    s.mx = m[0];
    s.my = m[1];
    s.a = q[0];
    s.b = q[1];
    s.c = q[2];
    s.o = static_cast<const scalar_t*>(p.opacities)[g];
    s.feature = static_cast<const scalar_t*>(p.features) + g * p.channels;
    // alpha >= 1/255 needs o exp(-sigma) >= 1/255, i.e. sigma <= ln(255 o) (-inf when o = 0).
    s.sigma_cutoff = std::log(255.0 * static_cast<double>(s.o)) + kSigmaCutoffMargin;
    // Pixel centres j + 0.5 within the radius of the mean, plus one pixel of slack per side (the
    // radii bound the alpha >= 1/255 region; the slack absorbs rounding at its edge). Kept in
    // double and clamped to a tile before any conversion, so huge radii cannot overflow.
    const double rx = static_cast<double>(p.radii[2 * g]);
    const double ry = static_cast<double>(p.radii[2 * g + 1]);
    s.col_lo = std::floor(static_cast<double>(s.mx) - rx - 0.5);
    s.col_hi = std::ceil(static_cast<double>(s.mx) + rx - 0.5);
    s.row_lo = std::floor(static_cast<double>(s.my) - ry - 0.5);
    s.row_hi = std::ceil(static_cast<double>(s.my) + ry - 0.5);
    return s;
}

// The pixels of one tile a Gaussian can reach (inclusive ranges).
struct Footprint {
    int64_t jlo, jhi, ilo, ihi;
    bool empty() const { return jlo > jhi || ilo > ihi; }
};

template <typename scalar_t>
inline Footprint clip(const Splat<scalar_t>& s, const TileRect& r) {
    Footprint f;
    f.jlo = static_cast<int64_t>(std::max<double>(static_cast<double>(r.x0), s.col_lo));
    f.jhi = static_cast<int64_t>(std::min<double>(static_cast<double>(r.x1 - 1), s.col_hi));
    f.ilo = static_cast<int64_t>(std::max<double>(static_cast<double>(r.y0), s.row_lo));
    f.ihi = static_cast<int64_t>(std::min<double>(static_cast<double>(r.y1 - 1), s.row_hi));
    return f;
}

// Evaluation of one Gaussian at one pixel centre, in the oracle's operation order.
template <typename scalar_t>
struct Eval {
    scalar_t dx, dy, vis, alpha;
    bool unclamped;  // o * vis <= alpha_max: alpha depends on o and sigma (clamp passes grad)
};

template <typename scalar_t>
inline bool evaluate(const Splat<scalar_t>& s, scalar_t px, scalar_t py, Eval<scalar_t>& e) {
    e.dx = px - s.mx;
    e.dy = py - s.my;
    const scalar_t sigma = static_cast<scalar_t>(0.5) * (s.a * e.dx * e.dx + s.c * e.dy * e.dy) + s.b * e.dx * e.dy;
    if (!(sigma >= 0) || static_cast<double>(sigma) > s.sigma_cutoff) return false;
    e.vis = std::exp(-sigma);
    const scalar_t raw = s.o * e.vis;
    e.unclamped = raw <= Rules<scalar_t>::alpha_max;
    e.alpha = e.unclamped ? raw : Rules<scalar_t>::alpha_max;
    return e.alpha >= Rules<scalar_t>::alpha_min;
}

// Runs fn(item, worker) for item in [0, n) on `threads` workers with a dynamic schedule. An
// exception in any worker stops the others and is rethrown here after all have joined; if a
// thread cannot be started, the workers already running finish the items.
void parallel_items(int64_t n, int64_t threads, const std::function<void(int64_t, int64_t)>& fn) {
    threads = std::max<int64_t>(1, std::min<int64_t>(threads, n));
    if (threads == 1) {
        for (int64_t i = 0; i < n; ++i) fn(i, 0);
        return;
    }
    std::atomic<int64_t> next{0};
    std::mutex error_mutex;
    std::exception_ptr error;
    auto worker = [&](int64_t w) {
        try {
            for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i, w);
        } catch (...) {
            std::lock_guard<std::mutex> lock(error_mutex);
            if (!error) error = std::current_exception();
            next.store(n);
        }
    };
    std::vector<std::thread> pool;
    pool.reserve(static_cast<size_t>(threads - 1));
    for (int64_t w = 1; w < threads; ++w) {
        try {
            pool.emplace_back(worker, w);
        } catch (const std::system_error&) {
            break;
        }
    }
    worker(0);
    for (auto& t : pool) t.join();
    if (error) std::rethrow_exception(error);
}

template <typename scalar_t>
struct ForwardOut {
    scalar_t* image;       // [H, W, C]
    scalar_t* alpha;       // [H, W]
    double* transmittance; // [H, W] final T (double, see header)
    int32_t* last;         // [H, W] 1 + position in the tile list of the last contributor (0: none)
};

template <typename scalar_t>
struct ForwardScratch {
    std::vector<double> T;
    std::vector<double> accum;
    std::vector<int32_t> last;
    std::vector<uint8_t> done;
};

template <typename scalar_t>
void forward_tile(const Problem& p, const Splat<scalar_t>* splats, int64_t tile, const ForwardOut<scalar_t>& out,
                  ForwardScratch<scalar_t>& s) {
    const TileRect r = tile_rect(p, tile);
    const int64_t npix = r.pixels();
    const int64_t C = p.channels;
    s.T.assign(npix, 1.0);
    s.accum.assign(npix * C, 0.0);
    s.last.assign(npix, 0);
    s.done.assign(npix, 0);
    int64_t alive = npix;
    const int64_t begin = p.offsets[tile];
    const int64_t end = p.offsets[tile + 1];
    for (int64_t k = begin; k < end && alive > 0; ++k) {
        const Splat<scalar_t>& g = splats[p.gaussian_ids[k]];
        const Footprint fp = clip(g, r);
        if (fp.empty()) continue;
        const int32_t position = static_cast<int32_t>(k - begin + 1);
        for (int64_t i = fp.ilo; i <= fp.ihi; ++i) {
            const scalar_t py = static_cast<scalar_t>(i) + static_cast<scalar_t>(0.5);
            const int64_t row = (i - r.y0) * r.width() - r.x0;
            for (int64_t j = fp.jlo; j <= fp.jhi; ++j) {
                const int64_t q = row + j;
                if (s.done[q]) continue;
                Eval<scalar_t> e;
                if (!evaluate(g, static_cast<scalar_t>(j) + static_cast<scalar_t>(0.5), py, e)) continue;
                const double T = s.T[q];
                const double next_T = T * static_cast<double>(static_cast<scalar_t>(1) - e.alpha);
                if (static_cast<scalar_t>(next_T) <= Rules<scalar_t>::transmittance_min) {
                    s.done[q] = 1;
                    --alive;
                    continue;
                }
                const scalar_t w = e.alpha * static_cast<scalar_t>(T);
                double* acc = &s.accum[q * C];
                for (int64_t ch = 0; ch < C; ++ch) acc[ch] += static_cast<double>(g.feature[ch] * w);
                s.T[q] = next_T;
                s.last[q] = position;
            }
        }
    }
    for (int64_t i = r.y0; i < r.y1; ++i) {
        for (int64_t j = r.x0; j < r.x1; ++j) {
            const int64_t q = (i - r.y0) * r.width() + (j - r.x0);
            const int64_t pix = i * p.width + j;
            for (int64_t ch = 0; ch < C; ++ch) out.image[pix * C + ch] = static_cast<scalar_t>(s.accum[q * C + ch]);
            out.alpha[pix] = static_cast<scalar_t>(1.0 - s.T[q]);
            out.transmittance[pix] = s.T[q];
            out.last[pix] = s.last[q];
        }
    }
}

template <typename scalar_t>
struct BackwardIn {
    const double* transmittance; // [H, W]
    const int32_t* last;         // [H, W]
    const scalar_t* grad_image;  // [H, W, C]
    const scalar_t* grad_alpha;  // [H, W]
};

template <typename scalar_t>
struct BackwardScratch {
    std::vector<double> T, T_final, buffer;  // buffer: sum of f w behind the current Gaussian
    std::vector<scalar_t> g_img, g_alpha;
    std::vector<int32_t> last;
    std::vector<double> g_feature;
};

// Slot layout per intersection: [means2d x, y | conic a, b, c | opacity | features 0..C-1].
constexpr int64_t kSlotFixed = 6;

template <typename scalar_t>
void backward_tile(const Problem& p, const Splat<scalar_t>* splats, int64_t tile, const BackwardIn<scalar_t>& in,
                   scalar_t* slots, BackwardScratch<scalar_t>& s) {
    const TileRect r = tile_rect(p, tile);
    const int64_t npix = r.pixels();
    const int64_t C = p.channels;
    const int64_t stride = kSlotFixed + C;
    s.T.resize(npix);
    s.T_final.resize(npix);
    s.last.resize(npix);
    s.g_alpha.resize(npix);
    s.g_img.resize(npix * C);
    s.buffer.assign(npix * C, 0.0);
    s.g_feature.resize(C);
    int32_t max_last = 0;
    for (int64_t i = r.y0; i < r.y1; ++i) {
        for (int64_t j = r.x0; j < r.x1; ++j) {
            const int64_t q = (i - r.y0) * r.width() + (j - r.x0);
            const int64_t pix = i * p.width + j;
            s.T[q] = s.T_final[q] = in.transmittance[pix];
            s.last[q] = in.last[pix];
            s.g_alpha[q] = in.grad_alpha[pix];
            for (int64_t ch = 0; ch < C; ++ch) s.g_img[q * C + ch] = in.grad_image[pix * C + ch];
            max_last = std::max(max_last, s.last[q]);
        }
    }
    const int64_t begin = p.offsets[tile];
    for (int64_t k = begin + max_last - 1; k >= begin; --k) {
        const Splat<scalar_t>& g = splats[p.gaussian_ids[k]];
        const Footprint fp = clip(g, r);
        scalar_t* slot = slots + k * stride;
        if (fp.empty()) continue;  // slot stays zero
        const int32_t position = static_cast<int32_t>(k - begin);
        double g_mx = 0, g_my = 0, g_a = 0, g_b = 0, g_c = 0, g_o = 0;
        std::fill(s.g_feature.begin(), s.g_feature.end(), 0.0);
        for (int64_t i = fp.ilo; i <= fp.ihi; ++i) {
            const scalar_t py = static_cast<scalar_t>(i) + static_cast<scalar_t>(0.5);
            const int64_t row = (i - r.y0) * r.width() - r.x0;
            for (int64_t j = fp.jlo; j <= fp.jhi; ++j) {
                const int64_t q = row + j;
                if (position >= s.last[q]) continue;  // behind this pixel's last contributor
                Eval<scalar_t> e;
                if (!evaluate(g, static_cast<scalar_t>(j) + static_cast<scalar_t>(0.5), py, e)) continue;
                const double one_minus = static_cast<double>(static_cast<scalar_t>(1) - e.alpha);
                const double inv_one_minus = 1.0 / one_minus;
                const double T = s.T[q] * inv_one_minus;  // transmittance in front of this Gaussian
                const double w = static_cast<double>(e.alpha) * T;
                const scalar_t* gi = &s.g_img[q * C];
                double* buf = &s.buffer[q * C];
                // d image / d alpha_i = f_i T_i - (sum_{j>i} f_j w_j) / (1 - alpha_i);
                // d (1 - T_final) / d alpha_i = T_final / (1 - alpha_i).
                double front = 0.0, behind = static_cast<double>(s.g_alpha[q]) * s.T_final[q];
                for (int64_t ch = 0; ch < C; ++ch) {
                    const double f = static_cast<double>(g.feature[ch]);
                    const double gc = static_cast<double>(gi[ch]);
                    s.g_feature[ch] += w * gc;
                    front += gc * f;
                    behind -= gc * buf[ch];
                    buf[ch] += f * w;
                }
                const double g_alpha = front * T + behind * inv_one_minus;
                s.T[q] = T;
                if (!e.unclamped) continue;  // alpha clamped at 0.999: no gradient to o, sigma
                const double vis = static_cast<double>(e.vis);
                g_o += g_alpha * vis;
                const double g_sigma = -g_alpha * static_cast<double>(g.o) * vis;
                const double dx = static_cast<double>(e.dx);
                const double dy = static_cast<double>(e.dy);
                g_a += g_sigma * 0.5 * dx * dx;
                g_b += g_sigma * dx * dy;
                g_c += g_sigma * 0.5 * dy * dy;
                // dx = px - mx, so d sigma / d mx = -(a dx + b dy).
                g_mx -= g_sigma * (static_cast<double>(g.a) * dx + static_cast<double>(g.b) * dy);
                g_my -= g_sigma * (static_cast<double>(g.b) * dx + static_cast<double>(g.c) * dy);
            }
        }
        slot[0] = static_cast<scalar_t>(g_mx);
        slot[1] = static_cast<scalar_t>(g_my);
        slot[2] = static_cast<scalar_t>(g_a);
        slot[3] = static_cast<scalar_t>(g_b);
        slot[4] = static_cast<scalar_t>(g_c);
        slot[5] = static_cast<scalar_t>(g_o);
        for (int64_t ch = 0; ch < C; ++ch) slot[kSlotFixed + ch] = static_cast<scalar_t>(s.g_feature[ch]);
    }
}

template <typename scalar_t>
struct Gradients {
    scalar_t* means2d;   // [N, 2]
    scalar_t* conics;    // [N, 3]
    scalar_t* opacities; // [N]
    scalar_t* features;  // [N, C]
};

// Sums the slots of every Gaussian in increasing intersection order. Gaussians are split into
// contiguous blocks, one per work item; each item scans all intersections and keeps its own, so
// the order of every sum is fixed regardless of the number of threads.
template <typename scalar_t>
void reduce_slots(const Problem& p, const scalar_t* slots, int64_t threads, const Gradients<scalar_t>& out) {
    const int64_t N = p.num_gaussians;
    const int64_t C = p.channels;
    const int64_t stride = kSlotFixed + C;
    const int64_t M = p.offsets[p.tiles_x * p.tiles_y];
    const int64_t blocks = std::max<int64_t>(1, std::min<int64_t>(threads, N));
    const int64_t per_block = (N + blocks - 1) / blocks;
    parallel_items(blocks, threads, [&](int64_t block, int64_t) {
        const int64_t lo = block * per_block;
        const int64_t hi = std::min(N, lo + per_block);
        if (lo >= hi) return;
        std::vector<double> sums(static_cast<size_t>((hi - lo) * stride), 0.0);
        for (int64_t k = 0; k < M; ++k) {
            const int64_t g = p.gaussian_ids[k];
            if (g < lo || g >= hi) continue;
            double* dst = &sums[(g - lo) * stride];
            const scalar_t* src = slots + k * stride;
            for (int64_t v = 0; v < stride; ++v) dst[v] += static_cast<double>(src[v]);
        }
        for (int64_t g = lo; g < hi; ++g) {
            const double* src = &sums[(g - lo) * stride];
            out.means2d[2 * g] = static_cast<scalar_t>(src[0]);
            out.means2d[2 * g + 1] = static_cast<scalar_t>(src[1]);
            out.conics[3 * g] = static_cast<scalar_t>(src[2]);
            out.conics[3 * g + 1] = static_cast<scalar_t>(src[3]);
            out.conics[3 * g + 2] = static_cast<scalar_t>(src[4]);
            out.opacities[g] = static_cast<scalar_t>(src[5]);
            for (int64_t ch = 0; ch < C; ++ch) out.features[g * C + ch] = static_cast<scalar_t>(src[kSlotFixed + ch]);
        }
    });
}

// ---- Tile binning (same lists as tiles.bin_gaussians, without a global sort of intersections) ----
//
// A visible Gaussian is listed in every tile its box [m - r, m + r] touches, with the tile range
// computed exactly as tiles.tile_ranges does (float64 floor/ceil of (m -/+ r) / tile_size, clamped
// to the grid). Lists are filled by walking the visible Gaussians in a stable depth order, so each
// tile's list is front to back with ties by Gaussian index: a counting sort, O(N log N + M).

struct BinProblem {
    const int32_t* radii;     // [N, 2]
    const uint8_t* visible;   // [N]
    int64_t num_gaussians;
    int64_t tile_size, tiles_x, tiles_y;
};

struct TileSpan {
    int64_t x0, x1, y0, y1;  // tiles [x0, x1) x [y0, y1)
};

inline int64_t clamp_tile(double v, int64_t hi) {
    return static_cast<int64_t>(std::min<double>(static_cast<double>(hi), std::max(0.0, v)));
}

template <typename scalar_t>
bool tile_span(const BinProblem& b, const scalar_t* means2d, int64_t g, TileSpan& s) {
    if (!b.visible[g]) return false;
    const double mx = static_cast<double>(means2d[2 * g]);
    const double my = static_cast<double>(means2d[2 * g + 1]);
    if (!std::isfinite(mx) || !std::isfinite(my)) return false;
    const double rx = static_cast<double>(b.radii[2 * g]);
    const double ry = static_cast<double>(b.radii[2 * g + 1]);
    const double ts = static_cast<double>(b.tile_size);
    s.x0 = clamp_tile(std::floor((mx - rx) / ts), b.tiles_x);
    s.x1 = clamp_tile(std::ceil((mx + rx) / ts), b.tiles_x);
    s.y0 = clamp_tile(std::floor((my - ry) / ts), b.tiles_y);
    s.y1 = clamp_tile(std::ceil((my + ry) / ts), b.tiles_y);
    return s.x1 > s.x0 && s.y1 > s.y0;
}

template <typename scalar_t>
int64_t bin_count(const BinProblem& b, const scalar_t* means2d, int64_t* offsets) {
    const int64_t tiles = b.tiles_x * b.tiles_y;
    std::fill(offsets, offsets + tiles + 1, int64_t(0));
    TileSpan s;
    for (int64_t g = 0; g < b.num_gaussians; ++g) {
        if (!tile_span(b, means2d, g, s)) continue;
        for (int64_t ty = s.y0; ty < s.y1; ++ty)
            for (int64_t tx = s.x0; tx < s.x1; ++tx) ++offsets[ty * b.tiles_x + tx + 1];
    }
    for (int64_t t = 0; t < tiles; ++t) offsets[t + 1] += offsets[t];
    return offsets[tiles];
}

template <typename scalar_t>
void bin_fill(const BinProblem& b, const scalar_t* means2d, const scalar_t* depths, const int64_t* offsets,
              int64_t* ids) {
    std::vector<int64_t> order;
    order.reserve(static_cast<size_t>(b.num_gaussians));
    TileSpan s;
    for (int64_t g = 0; g < b.num_gaussians; ++g)
        if (tile_span(b, means2d, g, s)) order.push_back(g);
    std::stable_sort(order.begin(), order.end(), [&](int64_t i, int64_t j) { return depths[i] < depths[j]; });
    std::vector<int64_t> cursor(offsets, offsets + b.tiles_x * b.tiles_y);
    for (int64_t g : order) {
        tile_span(b, means2d, g, s);
        for (int64_t ty = s.y0; ty < s.y1; ++ty)
            for (int64_t tx = s.x0; tx < s.x1; ++tx) ids[cursor[ty * b.tiles_x + tx]++] = g;
    }
}

BinProblem make_bin_problem(const int32_t* radii, const uint8_t* visible, int64_t n, int64_t width, int64_t height,
                            int64_t tile_size) {
    BinProblem b;
    b.radii = radii;
    b.visible = visible;
    b.num_gaussians = n;
    b.tile_size = tile_size;
    b.tiles_x = (width + tile_size - 1) / tile_size;
    b.tiles_y = (height + tile_size - 1) / tile_size;
    return b;
}

Problem make_problem(const void* means2d, const void* conics, const void* opacities, const void* features,
                     const int32_t* radii, int64_t n, int64_t c, const int64_t* offsets, const int64_t* ids,
                     int64_t width, int64_t height, int64_t tile_size) {
    Problem p;
    p.means2d = means2d;
    p.conics = conics;
    p.opacities = opacities;
    p.features = features;
    p.radii = radii;
    p.num_gaussians = n;
    p.channels = c;
    p.offsets = offsets;
    p.gaussian_ids = ids;
    p.width = width;
    p.height = height;
    p.tile_size = tile_size;
    p.tiles_x = (width + tile_size - 1) / tile_size;
    p.tiles_y = (height + tile_size - 1) / tile_size;
    return p;
}

// Splat parameters of every Gaussian, computed in parallel blocks (each entry written once).
template <typename scalar_t>
std::vector<Splat<scalar_t>> prepare_splats(const Problem& p, int64_t threads) {
    std::vector<Splat<scalar_t>> splats(static_cast<size_t>(p.num_gaussians));
    const int64_t block = 4096;
    parallel_items((p.num_gaussians + block - 1) / block, threads, [&](int64_t b, int64_t) {
        const int64_t end = std::min(p.num_gaussians, (b + 1) * block);
        for (int64_t g = b * block; g < end; ++g) splats[g] = prepare_splat<scalar_t>(p, g);
    });
    return splats;
}

template <typename scalar_t>
int forward(const Problem& p, int64_t threads, const ForwardOut<scalar_t>& out) {
    const int64_t workers = std::max<int64_t>(1, threads);
    const std::vector<Splat<scalar_t>> splats = prepare_splats<scalar_t>(p, workers);
    std::vector<ForwardScratch<scalar_t>> scratch(static_cast<size_t>(workers));
    parallel_items(p.tiles_x * p.tiles_y, workers,
                   [&](int64_t tile, int64_t w) { forward_tile<scalar_t>(p, splats.data(), tile, out, scratch[w]); });
    return 0;
}

template <typename scalar_t>
int backward(const Problem& p, int64_t threads, const BackwardIn<scalar_t>& in, const Gradients<scalar_t>& out) {
    const int64_t workers = std::max<int64_t>(1, threads);
    const int64_t M = p.offsets[p.tiles_x * p.tiles_y];
    std::vector<scalar_t> slots(static_cast<size_t>(M * (kSlotFixed + p.channels)), scalar_t(0));
    const std::vector<Splat<scalar_t>> splats = prepare_splats<scalar_t>(p, workers);
    std::vector<BackwardScratch<scalar_t>> scratch(static_cast<size_t>(workers));
    parallel_items(p.tiles_x * p.tiles_y, workers, [&](int64_t tile, int64_t w) {
        backward_tile<scalar_t>(p, splats.data(), tile, in, slots.data(), scratch[w]);
    });
    reduce_slots<scalar_t>(p, slots.data(), workers, out);
    return 0;
}

// C entry points return 0 on success and a non-zero code on failure (no exception may cross).
template <typename F>
int guarded(F&& f) {
    try {
        return f();
    } catch (const std::bad_alloc&) {
        return 2;
    } catch (...) {
        return 3;
    }
}

}  // namespace

#define RK_ENTRY_POINTS(SUFFIX, SCALAR)                                                                         \
    extern "C" int rk_forward_##SUFFIX(const SCALAR* means2d, const SCALAR* conics, const SCALAR* opacities,    \
                                       const SCALAR* features, const int32_t* radii, int64_t n, int64_t c,      \
                                       const int64_t* offsets, const int64_t* ids, int64_t width,               \
                                       int64_t height, int64_t tile_size, int64_t threads, SCALAR* image,       \
                                       SCALAR* alpha, double* transmittance, int32_t* last) {                   \
        return guarded([&] {                                                                                    \
            const Problem p = make_problem(means2d, conics, opacities, features, radii, n, c, offsets, ids,      \
                                           width, height, tile_size);                                           \
            return forward<SCALAR>(p, threads, ForwardOut<SCALAR>{image, alpha, transmittance, last});          \
        });                                                                                                     \
    }                                                                                                           \
    extern "C" int rk_backward_##SUFFIX(const SCALAR* means2d, const SCALAR* conics, const SCALAR* opacities,   \
                                        const SCALAR* features, const int32_t* radii, int64_t n, int64_t c,     \
                                        const int64_t* offsets, const int64_t* ids, int64_t width,              \
                                        int64_t height, int64_t tile_size, int64_t threads,                     \
                                        const double* transmittance, const int32_t* last,                       \
                                        const SCALAR* grad_image, const SCALAR* grad_alpha,                     \
                                        SCALAR* grad_means2d, SCALAR* grad_conics, SCALAR* grad_opacities,      \
                                        SCALAR* grad_features) {                                                \
        return guarded([&] {                                                                                    \
            const Problem p = make_problem(means2d, conics, opacities, features, radii, n, c, offsets, ids,      \
                                           width, height, tile_size);                                           \
            return backward<SCALAR>(p, threads, BackwardIn<SCALAR>{transmittance, last, grad_image, grad_alpha}, \
                                    Gradients<SCALAR>{grad_means2d, grad_conics, grad_opacities, grad_features}); \
        });                                                                                                     \
    }

#define RK_BIN_ENTRY_POINTS(SUFFIX, SCALAR)                                                                     \
    extern "C" int64_t rk_bin_count_##SUFFIX(const SCALAR* means2d, const int32_t* radii, const uint8_t* visible,  \
                                             int64_t n, int64_t width, int64_t height, int64_t tile_size,         \
                                             int64_t* offsets) {                                                  \
        try {                                                                                                     \
            return bin_count(make_bin_problem(radii, visible, n, width, height, tile_size), means2d, offsets);     \
        } catch (...) {                                                                                           \
            return -1;                                                                                            \
        }                                                                                                         \
    }                                                                                                             \
    extern "C" int rk_bin_fill_##SUFFIX(const SCALAR* means2d, const int32_t* radii, const uint8_t* visible,       \
                                        const SCALAR* depths, int64_t n, int64_t width, int64_t height,           \
                                        int64_t tile_size, const int64_t* offsets, int64_t* ids) {                \
        return guarded([&] {                                                                                      \
            bin_fill(make_bin_problem(radii, visible, n, width, height, tile_size), means2d, depths, offsets, ids); \
            return 0;                                                                                             \
        });                                                                                                       \
    }

RK_BIN_ENTRY_POINTS(f32, float)
RK_BIN_ENTRY_POINTS(f64, double)
RK_ENTRY_POINTS(f32, float)
RK_ENTRY_POINTS(f64, double)

extern "C" int rk_abi_version() { return kAbiVersion; }
