// Products of bilinear plane samples (HexPlane's inner loop) on the CPU: forward and backward.
//
// Compiled on first use by baselines/fourdgs/plane_kernel.py into a plain shared library (no
// Python or torch headers) and called through ctypes with raw pointers to contiguous tensors.
// It computes exactly what the torch path of plane_lookup.py computes (that path is the oracle of
// the tests): for every point n and plane p, a bilinear sample of the plane at
// (coords[n, u_axis[p]], coords[n, v_axis[p]]) in [-1, 1] with grid_sample's align_corners=True
// and border padding (a clamped coordinate gets no gradient); consecutive groups of `group` planes
// are multiplied elementwise and the groups' products concatenated:
//     out[n, g*C + c] = prod_{p in group g} sum_{k<4} w_k(n, p) * table[row_k(n, p), c].
// The planes are row blocks of one channels-last table [cells, C] (PlaneLayout in Python).
//
// Work split. Forward: points are split into blocks, one thread per block (every output row is
// written by one thread). Backward: the coordinate gradients are per point, split the same way;
// the table gradient is a scatter, so it runs in two phases per chunk of points: phase 1
// (threads over point blocks) writes each (point, plane) sample gradient into a buffer, phase 2
// (threads over planes; planes own disjoint table rows) adds them into the table in point order.
// Every table cell therefore sums its contributions in point order whatever the thread count, and
// 1, 2 or 16 threads give bitwise identical gradients. A single thread skips the buffer and
// scatters directly in the same order.
//
// Threads: std::thread per call (torch's OpenMP pool is not touched, so no second OpenMP runtime
// is loaded); calls are a few milliseconds, thread start-up tens of microseconds.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <functional>
#include <mutex>
#include <new>
#include <system_error>
#include <thread>
#include <type_traits>
#include <vector>

namespace {

constexpr int kAbiVersion = 1;
constexpr int kOk = 0;
constexpr int kOutOfMemory = 2;
constexpr int kFailed = 3;
// Points per chunk of the two-phase backward: bounds the sample-gradient buffer
// (chunk x planes x C values; 8192 x 12 x 16 floats = 6 MB).
constexpr int64_t kChunkPoints = 8192;
// Points per work item of the point-parallel loops.
constexpr int64_t kBlockPoints = 256;

struct Layout {
    const int64_t* u_axis;
    const int64_t* v_axis;
    const int64_t* width;
    const int64_t* height;
    const int64_t* offset;
    int64_t planes;
    int64_t group;
    int64_t dims;      // coordinates per point
    int64_t channels;  // C
    // Distinct (coordinate, size) pairs the planes sample along (HexPlane: 7 for 24 plane axes),
    // so that a point's axis cells are computed once and shared by the planes.
    std::vector<int64_t> slot_axis, slot_size, u_slot, v_slot;

    Layout(const int64_t* u, const int64_t* v, const int64_t* w, const int64_t* h, const int64_t* o, int64_t p,
           int64_t g, int64_t d, int64_t c)
        : u_axis(u), v_axis(v), width(w), height(h), offset(o), planes(p), group(g), dims(d), channels(c) {
        for (int64_t plane = 0; plane < planes; ++plane) {
            u_slot.push_back(slot_of(u_axis[plane], width[plane]));
            v_slot.push_back(slot_of(v_axis[plane], height[plane]));
        }
    }

    int64_t slots() const { return static_cast<int64_t>(slot_axis.size()); }

  private:
    int64_t slot_of(int64_t axis, int64_t size) {
        for (int64_t s = 0; s < slots(); ++s)
            if (slot_axis[s] == axis && slot_size[s] == size) return s;
        slot_axis.push_back(axis);
        slot_size.push_back(size);
        return slots() - 1;
    }
};

// align_corners sampling along one axis (plane_lookup._AxisCells): top-left index, fraction and
// whether the coordinate lies strictly inside (border padding gives no gradient where clamped).
template <typename scalar_t>
struct AxisCell {
    int64_t index;
    scalar_t frac;
    bool inside;
};

template <typename scalar_t>
inline AxisCell<scalar_t> axis_cell(scalar_t coord, int64_t size) {
    const scalar_t extent = static_cast<scalar_t>(size - 1);
    const scalar_t scaled = (coord + scalar_t(1)) * (scalar_t(0.5) * extent);
    AxisCell<scalar_t> cell;
    cell.inside = scaled > scalar_t(0) && scaled < extent;
    // clamp; a NaN coordinate goes to the border (the caller validates coordinates)
    scalar_t clamped = scaled > scalar_t(0) ? scaled : scalar_t(0);
    clamped = clamped < extent ? clamped : extent;
    // floor by truncation (clamped >= 0): std::floor is a libm call on baseline x86-64
    scalar_t index = static_cast<scalar_t>(static_cast<int64_t>(clamped));
    const scalar_t last = extent - scalar_t(1) > scalar_t(0) ? extent - scalar_t(1) : scalar_t(0);
    index = index < last ? index : last;
    cell.index = static_cast<int64_t>(index);
    cell.frac = clamped - index;
    return cell;
}

// One point's four corner rows and bilinear weights on one plane (plane_lookup._PlaneCells).
template <typename scalar_t>
struct Corners {
    int64_t row[4];
    scalar_t weight[4];
    AxisCell<scalar_t> u, v;
};

// The axis cells of one point for every slot of the layout: cells[s] for s < L.slots().
template <typename scalar_t>
inline void point_cells(const scalar_t* point, const Layout& L, AxisCell<scalar_t>* cells) {
    for (int64_t s = 0; s < L.slots(); ++s) cells[s] = axis_cell(point[L.slot_axis[s]], L.slot_size[s]);
}

// The corner rows and bilinear weights on plane p of a point with axis cells u and v.
template <typename scalar_t>
inline Corners<scalar_t> corners_of_cells(const AxisCell<scalar_t>& u, const AxisCell<scalar_t>& v, const Layout& L,
                                          int64_t p) {
    Corners<scalar_t> k;
    const int64_t w = L.width[p], h = L.height[p];
    k.u = u;
    k.v = v;
    const int64_t base = L.offset[p] + k.v.index * w + k.u.index;
    const int64_t col = w > 1 ? 1 : 0, row = h > 1 ? w : 0;
    k.row[0] = base;
    k.row[1] = base + col;
    k.row[2] = base + row;
    k.row[3] = base + col + row;
    const scalar_t fu = k.u.frac, fv = k.v.frac, gu = scalar_t(1) - fu, gv = scalar_t(1) - fv;
    k.weight[0] = gu * gv;
    k.weight[1] = fu * gv;
    k.weight[2] = gu * fv;
    k.weight[3] = fu * fv;
    return k;
}

template <typename scalar_t>
inline Corners<scalar_t> corners_of(const AxisCell<scalar_t>* cells, const Layout& L, int64_t p) {
    return corners_of_cells(cells[L.u_slot[p]], cells[L.v_slot[p]], L, p);
}

// ---- Channel loops ------------------------------------------------------------------------------
//
// Every per-channel loop runs on 16-byte vectors (4 floats or 2 doubles; GCC / Clang vector
// extensions, so baseline x86-64 SSE2 or NEON) plus a scalar tail, through for_channels: the body
// is a generic lambda called with a vector or a scalar tag. Written out because the compiler did
// not vectorise the dot products (a reduction needs reassociation, which -O3 without fast-math
// does not do) and versioned the others for aliasing. Sums keep one running value per lane and
// add the lanes in a fixed order: results do not depend on the thread count.

template <typename scalar_t>
struct Simd {
    typedef scalar_t vec __attribute__((vector_size(16)));
    static constexpr int64_t kWidth = 16 / static_cast<int64_t>(sizeof(scalar_t));
};

template <typename T, typename scalar_t>
inline T load(const scalar_t* p) {
    T v;
    std::memcpy(&v, p, sizeof(T));
    return v;
}

template <typename T, typename scalar_t>
inline void store(scalar_t* p, T v) {
    std::memcpy(p, &v, sizeof(T));
}

// Calls body(c, T{}) with T the vector type for the full vectors of [0, C), then the scalar type.
template <typename scalar_t, typename Body>
inline void for_channels(int64_t C, Body&& body) {
    using V = typename Simd<scalar_t>::vec;
    constexpr int64_t W = Simd<scalar_t>::kWidth;
    int64_t c = 0;
    for (; c + W <= C; c += W) body(c, V{});
    for (; c < C; ++c) body(c, scalar_t{});
}

// Running sum of vectors and scalars; total() adds the lanes in a fixed order, then the tail.
template <typename scalar_t>
struct LaneSum {
    typename Simd<scalar_t>::vec lanes{};
    scalar_t tail = 0;
    void add(typename Simd<scalar_t>::vec v) { lanes += v; }
    void add(scalar_t v) { tail += v; }
    scalar_t total() const {
        scalar_t sum = 0;
        for (int64_t l = 0; l < Simd<scalar_t>::kWidth; ++l) sum += lanes[l];
        return sum + tail;
    }
};

// out[c] = sum_k weight[k] * table[row[k], c], summed in corner order (embedding_bag's order).
template <typename scalar_t>
inline void sample(const scalar_t* table, const Corners<scalar_t>& k, int64_t C, scalar_t* out) {
    const scalar_t* r0 = table + k.row[0] * C;
    const scalar_t* r1 = table + k.row[1] * C;
    const scalar_t* r2 = table + k.row[2] * C;
    const scalar_t* r3 = table + k.row[3] * C;
    const scalar_t w0 = k.weight[0], w1 = k.weight[1], w2 = k.weight[2], w3 = k.weight[3];
    for_channels<scalar_t>(C, [&](int64_t c, auto tag) {
        using T = decltype(tag);
        store<T>(out + c, ((w0 * load<T>(r0 + c) + w1 * load<T>(r1 + c)) + w2 * load<T>(r2 + c)) + w3 * load<T>(r3 + c));
    });
}

// a[c] = a[c] * b[c]
template <typename scalar_t>
inline void multiply_into(scalar_t* a, const scalar_t* b, int64_t C) {
    for_channels<scalar_t>(C, [&](int64_t c, auto tag) {
        using T = decltype(tag);
        store<T>(a + c, load<T>(a + c) * load<T>(b + c));
    });
}

// out[c] = a[c] * b[c]
template <typename scalar_t>
inline void multiply(const scalar_t* a, const scalar_t* b, scalar_t* out, int64_t C) {
    for_channels<scalar_t>(C, [&](int64_t c, auto tag) {
        using T = decltype(tag);
        store<T>(out + c, load<T>(a + c) * load<T>(b + c));
    });
}

// Runs fn(item) for item in [0, n) on up to `threads` workers (dynamic schedule). An exception in
// a worker stops the others and is rethrown after all have joined.
void parallel_items(int64_t n, int64_t threads, const std::function<void(int64_t)>& fn) {
    threads = std::max<int64_t>(1, std::min<int64_t>(threads, n));
    if (threads == 1) {
        for (int64_t i = 0; i < n; ++i) fn(i);
        return;
    }
    std::atomic<int64_t> next{0};
    std::mutex error_mutex;
    std::exception_ptr error;
    auto worker = [&]() {
        try {
            for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i);
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
            pool.emplace_back(worker);
        } catch (const std::system_error&) {
            break;  // the workers already running finish the items
        }
    }
    worker();
    for (auto& t : pool) t.join();
    if (error) std::rethrow_exception(error);
}

// Calls fn(first, last) on blocks of kBlockPoints points of [begin, end), in parallel.
void parallel_points(int64_t begin, int64_t end, int64_t threads,
                     const std::function<void(int64_t, int64_t)>& fn) {
    const int64_t blocks = (end - begin + kBlockPoints - 1) / kBlockPoints;
    parallel_items(blocks, threads, [&](int64_t b) {
        const int64_t first = begin + b * kBlockPoints;
        fn(first, std::min(end, first + kBlockPoints));
    });
}

template <typename scalar_t, int64_t kC>
void forward(const scalar_t* table, const scalar_t* coords, int64_t n, const Layout& L, int64_t threads,
             scalar_t* out) {
    const int64_t C = kC > 0 ? kC : L.channels, groups = L.planes / L.group, width = groups * C;
    parallel_points(0, n, threads, [&](int64_t first, int64_t last) {
        std::vector<scalar_t> s(static_cast<size_t>(C));
        std::vector<AxisCell<scalar_t>> cells(static_cast<size_t>(L.slots()));
        for (int64_t i = first; i < last; ++i) {
            point_cells(coords + i * L.dims, L, cells.data());
            for (int64_t g = 0; g < groups; ++g) {
                scalar_t* product = out + i * width + g * C;
                for (int64_t j = 0; j < L.group; ++j) {
                    const int64_t p = g * L.group + j;
                    const Corners<scalar_t> k = corners_of(cells.data(), L, p);
                    if (j == 0) {
                        sample(table, k, C, product);
                    } else {
                        sample(table, k, C, s.data());
                        multiply_into(product, s.data(), C);
                    }
                }
            }
        }
    });
}

// Per-point backward work for one point: fills grad_samples[p * C + c] (the gradient reaching each
// plane's sample, grad * product of the group's other samples, taken with prefix and suffix
// products so that zeros are exact) and adds the coordinate gradients of the point.
template <typename scalar_t, int64_t kC>
struct PointBackward {
    const scalar_t* table;
    const Layout& L;
    const uint8_t* want_axis;  // [dims] or nullptr: no coordinate gradient
    std::vector<scalar_t> samples, suffix, prefix;
    std::vector<AxisCell<scalar_t>> cells;
    std::vector<Corners<scalar_t>> corners;  // [planes] of the last point run

    PointBackward(const scalar_t* table_, const Layout& layout, const uint8_t* want)
        : table(table_), L(layout), want_axis(want),
          samples(static_cast<size_t>(layout.group * layout.channels)),
          suffix(static_cast<size_t>(layout.group * layout.channels)),
          prefix(static_cast<size_t>(layout.channels)),
          cells(static_cast<size_t>(layout.slots())),
          corners(static_cast<size_t>(layout.planes)) {}

    void run(const scalar_t* point, const scalar_t* grad_out, scalar_t* grad_samples, scalar_t* grad_point) {
        const int64_t C = kC > 0 ? kC : L.channels, G = L.group, groups = L.planes / G;
        point_cells(point, L, cells.data());
        for (int64_t g = 0; g < groups; ++g) {
            for (int64_t j = 0; j < G; ++j) {
                corners[g * G + j] = corners_of(cells.data(), L, g * G + j);
                sample(table, corners[g * G + j], C, samples.data() + j * C);
            }
            // suffix[j] = prod_{i > j} samples[i]; the last has none
            for (int64_t j = G - 2; j >= 0; --j) {
                const scalar_t* next = samples.data() + (j + 1) * C;
                scalar_t* here = suffix.data() + j * C;
                if (j == G - 2) {
                    std::memcpy(here, next, sizeof(scalar_t) * C);
                } else {
                    multiply(suffix.data() + (j + 1) * C, next, here, C);
                }
            }
            const scalar_t* go = grad_out + g * C;
            std::memcpy(prefix.data(), go, sizeof(scalar_t) * C);
            for (int64_t j = 0; j < G; ++j) {
                scalar_t* gs = grad_samples + (g * G + j) * C;
                if (j == G - 1) {
                    std::memcpy(gs, prefix.data(), sizeof(scalar_t) * C);
                } else {
                    multiply(prefix.data(), suffix.data() + j * C, gs, C);
                    multiply_into(prefix.data(), samples.data() + j * C, C);
                }
                if (want_axis != nullptr) add_coordinate_grads(corners[g * G + j], g * G + j, gs, grad_point);
            }
        }
    }

    // d sample / d fu is gv (r1 - r0) + fv (r3 - r2), d sample / d fv is gu (r2 - r0) + fu (r3 - r1)
    // (the derivatives of the bilinear weights); the chain rule adds (size - 1) / 2, and nothing
    // where the coordinate was clamped.
    void add_coordinate_grads(const Corners<scalar_t>& k, int64_t p, const scalar_t* gs, scalar_t* grad_point) {
        const int64_t C = kC > 0 ? kC : L.channels;
        const scalar_t* r0 = table + k.row[0] * C;
        const scalar_t* r1 = table + k.row[1] * C;
        const scalar_t* r2 = table + k.row[2] * C;
        const scalar_t* r3 = table + k.row[3] * C;
        const scalar_t fu = k.u.frac, fv = k.v.frac, gu = scalar_t(1) - fu, gv = scalar_t(1) - fv;
        LaneSum<scalar_t> du, dv;
        for_channels<scalar_t>(C, [&](int64_t c, auto tag) {
            using T = decltype(tag);
            const T a0 = load<T>(r0 + c), a1 = load<T>(r1 + c), a2 = load<T>(r2 + c), a3 = load<T>(r3 + c);
            const T g = load<T>(gs + c);
            du.add((gv * (a1 - a0) + fv * (a3 - a2)) * g);
            dv.add((gu * (a2 - a0) + fu * (a3 - a1)) * g);
        });
        const int64_t ua = L.u_axis[p], va = L.v_axis[p];
        if (want_axis[ua] && k.u.inside)
            grad_point[ua] += du.total() * (scalar_t(0.5) * static_cast<scalar_t>(L.width[p] - 1));
        if (want_axis[va] && k.v.inside)
            grad_point[va] += dv.total() * (scalar_t(0.5) * static_cast<scalar_t>(L.height[p] - 1));
    }
};

// grad_table[row_k] += weight_k * grad_sample for one point's plane p, corners in order.
template <typename scalar_t>
inline void scatter(scalar_t* grad_table, const Corners<scalar_t>& k, const scalar_t* gs, int64_t C) {
    for (int q = 0; q < 4; ++q) {
        scalar_t* row = grad_table + k.row[q] * C;
        const scalar_t w = k.weight[q];
        for_channels<scalar_t>(C, [&](int64_t c, auto tag) {
            using T = decltype(tag);
            store<T>(row + c, load<T>(row + c) + w * load<T>(gs + c));
        });
    }
}

template <typename scalar_t, int64_t kC>
void backward(const scalar_t* table, const scalar_t* coords, int64_t n, const Layout& L, const scalar_t* grad_out,
              const uint8_t* want_axis, int64_t threads, scalar_t* grad_table, scalar_t* grad_coords) {
    const int64_t C = kC > 0 ? kC : L.channels, P = L.planes, width = (P / L.group) * C;
    if (threads <= 1 || grad_table == nullptr) {
        // No buffer: coordinate gradients are per point, and one thread scatters in point order.
        const int64_t workers = grad_table == nullptr ? threads : 1;
        parallel_points(0, n, workers, [&](int64_t first, int64_t last) {
            PointBackward<scalar_t, kC> work(table, L, want_axis);
            std::vector<scalar_t> gs(static_cast<size_t>(P * C));
            for (int64_t i = first; i < last; ++i) {
                const scalar_t* point = coords + i * L.dims;
                work.run(point, grad_out + i * width, gs.data(), grad_coords ? grad_coords + i * L.dims : nullptr);
                if (grad_table == nullptr) continue;
                for (int64_t p = 0; p < P; ++p) scatter(grad_table, work.corners[p], gs.data() + p * C, C);
            }
        });
        return;
    }
    const int64_t chunk = std::min(n, kChunkPoints);
    std::vector<scalar_t> buffer(static_cast<size_t>(chunk * P * C));
    for (int64_t begin = 0; begin < n; begin += chunk) {
        const int64_t end = std::min(n, begin + chunk);
        parallel_points(begin, end, threads, [&](int64_t first, int64_t last) {
            PointBackward<scalar_t, kC> work(table, L, want_axis);
            for (int64_t i = first; i < last; ++i) {
                work.run(coords + i * L.dims, grad_out + i * width, buffer.data() + (i - begin) * P * C,
                         grad_coords ? grad_coords + i * L.dims : nullptr);
            }
        });
        parallel_items(P, threads, [&](int64_t p) {
            AxisCell<scalar_t> cells[2];
            for (int64_t i = begin; i < end; ++i) {
                const scalar_t* point = coords + i * L.dims;
                cells[0] = axis_cell(point[L.u_axis[p]], L.width[p]);
                cells[1] = axis_cell(point[L.v_axis[p]], L.height[p]);
                scatter(grad_table, corners_of_cells(cells[0], cells[1], L, p), buffer.data() + ((i - begin) * P + p) * C, C);
            }
        });
    }
}

// Calls fn(std::integral_constant<int64_t, C>) for the common channel counts, so that the
// per-channel loops are compiled with a constant trip count (fully unrolled and vectorised), and
// fn(std::integral_constant<int64_t, 0>) (channels read at run time) for the others.
template <typename F>
void by_channels(int64_t channels, F&& fn) {
    switch (channels) {
        case 8: fn(std::integral_constant<int64_t, 8>{}); break;
        case 16: fn(std::integral_constant<int64_t, 16>{}); break;
        case 32: fn(std::integral_constant<int64_t, 32>{}); break;
        default: fn(std::integral_constant<int64_t, 0>{}); break;
    }
}

template <typename F>
int guarded(F&& fn) {
    try {
        fn();
        return kOk;
    } catch (const std::bad_alloc&) {
        return kOutOfMemory;
    } catch (...) {
        return kFailed;
    }
}

}  // namespace

// Entry points. Shapes: table [cells, C]; coords [n, dims]; layout arrays [planes]; out and
// grad_out [n, planes / group * C]; want_axis [dims] (1: that coordinate wants a gradient) or
// NULL; grad_table [cells, C] zero-filled, or NULL; grad_coords [n, dims] zero-filled, or NULL.
#define PK_ENTRY_POINTS(SUFFIX, SCALAR)                                                                            \
    extern "C" int pk_forward_##SUFFIX(const SCALAR* table, const SCALAR* coords, int64_t n, int64_t dims,         \
                                       int64_t channels, const int64_t* u_axis, const int64_t* v_axis,             \
                                       const int64_t* width, const int64_t* height, const int64_t* offset,         \
                                       int64_t planes, int64_t group, int64_t threads, SCALAR* out) {              \
        const Layout layout{u_axis, v_axis, width, height, offset, planes, group, dims, channels};                 \
        return guarded([&] { by_channels(channels, [&](auto kC) {                                                  \
            forward<SCALAR, decltype(kC)::value>(table, coords, n, layout, threads, out); }); });                  \
    }                                                                                                              \
    extern "C" int pk_backward_##SUFFIX(const SCALAR* table, const SCALAR* coords, int64_t n, int64_t dims,        \
                                        int64_t channels, const int64_t* u_axis, const int64_t* v_axis,            \
                                        const int64_t* width, const int64_t* height, const int64_t* offset,        \
                                        int64_t planes, int64_t group, int64_t threads, const SCALAR* grad_out,    \
                                        const uint8_t* want_axis, SCALAR* grad_table, SCALAR* grad_coords) {       \
        const Layout layout{u_axis, v_axis, width, height, offset, planes, group, dims, channels};                 \
        return guarded([&] { by_channels(channels, [&](auto kC) {                                                  \
            backward<SCALAR, decltype(kC)::value>(table, coords, n, layout, grad_out,                              \
                                                  grad_coords ? want_axis : nullptr, threads, grad_table,          \
                                                  grad_coords); }); });                                            \
    }

PK_ENTRY_POINTS(f32, float)
PK_ENTRY_POINTS(f64, double)

extern "C" int pk_abi_version() { return kAbiVersion; }
