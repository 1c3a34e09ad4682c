// chunkrt's fused CUDA kernels for the policy's transformer layers (policy/src/kernels.rs).
//
// Candle runs one kernel per op; these replace the op chains that dominate a denoising step at
// batch 1: Gemma RMSNorm / AdaRMSNorm with its modulation (and the gated residual before it),
// the Q/K/V head split with RoPE written straight into the KV cache, the gelu-tanh gate * up
// product, and the scaled, masked softmax of attention. Every kernel takes the model's dtype T
// (float or bf16) for activations, keeps statistics, modulation and softmax in f32 (as openpi
// does) and rounds once on the way out. Compiled to PTX by policy/build.rs (feature `cuda`).

#include <cuda_bf16.h>
#include <stdint.h>

__device__ __forceinline__ float to_f(float x) { return x; }
__device__ __forceinline__ float to_f(__nv_bfloat16 x) { return __bfloat162float(x); }
template <typename T> __device__ __forceinline__ T from_f(float x);
template <> __device__ __forceinline__ float from_f<float>(float x) { return x; }
template <> __device__ __forceinline__ __nv_bfloat16 from_f<__nv_bfloat16>(float x) {
  return __float2bfloat16(x);
}

// Sum of `v` over the block (blockDim.x a multiple of 32, at most 1024); every thread gets it.
__device__ __forceinline__ float block_sum(float v, float* shared) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffff, v, o);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  __syncthreads();
  if (lane == 0) shared[warp] = v;
  __syncthreads();
  float s = 0.f;
  for (int w = 0; w < warps; ++w) s += shared[w];
  return s;
}

__device__ __forceinline__ float block_max(float v, float* shared) {
  for (int o = 16; o > 0; o >>= 1) v = fmaxf(v, __shfl_xor_sync(0xffffffff, v, o));
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  __syncthreads();
  if (lane == 0) shared[warp] = v;
  __syncthreads();
  float m = shared[0];
  for (int w = 1; w < warps; ++w) m = fmaxf(m, shared[w]);
  return m;
}

// One block per row of width W (rows = B * rows_per_batch).
//   residual: x1 = x + y * gate (y null: x1 = x; gate null: x1 = x + y); x1 written when out_x1.
//   norm:     h = x1 * rsqrt(mean(x1^2) + eps) * alpha (alpha null: 1), then for AdaRMSNorm
//             h = h * (1 + scale) + shift with (scale, shift) = mod[b, 0:W], mod[b, W:2W].
//   gate:     gmod[b, 2W:3W] (the previous norm's modulation), gmod null: no gate.
// Statistics and modulation in f32; x1 is rounded to T before its statistics (as the unfused
// chain, which stores the residual in T, computes them).
template <typename T>
__device__ void add_norm(const T* __restrict__ x, const T* __restrict__ y, const float* __restrict__ gmod,
                         T* __restrict__ out_x1, T* __restrict__ out_h, const float* __restrict__ alpha,
                         const float* __restrict__ mod, int W, int rows_per_batch, float eps) {
  extern __shared__ float buf[];  // W floats of x1, then 32 for the reduction
  float* red = buf + W;
  const int row = blockIdx.x, b = row / rows_per_batch;
  const T* xr = x + (size_t)row * W;
  const T* yr = y ? y + (size_t)row * W : nullptr;
  const float* g = gmod ? gmod + (size_t)b * 3 * W + 2 * W : nullptr;
  float ss = 0.f;
  for (int i = threadIdx.x; i < W; i += blockDim.x) {
    float v = to_f(xr[i]);
    if (yr) v += g ? to_f(yr[i]) * g[i] : to_f(yr[i]);
    v = to_f(from_f<T>(v));
    buf[i] = v;
    if (out_x1) out_x1[(size_t)row * W + i] = from_f<T>(v);
    ss += v * v;
  }
  ss = block_sum(ss, red);
  const float r = rsqrtf(ss / (float)W + eps);
  const float* sc = mod ? mod + (size_t)b * 3 * W : nullptr;
  for (int i = threadIdx.x; i < W; i += blockDim.x) {
    float h = buf[i] * r;
    if (alpha) h *= alpha[i];
    if (sc) h = h * (1.f + sc[i]) + sc[W + i];
    out_h[(size_t)row * W + i] = from_f<T>(h);
  }
}

// x + y * gate (gate = gmod[b, 2W:3W], null: x + y); one block per row.
template <typename T>
__device__ void gated_add(const T* __restrict__ x, const T* __restrict__ y, const float* __restrict__ gmod,
                          T* __restrict__ out, int W, int rows_per_batch) {
  const int row = blockIdx.x, b = row / rows_per_batch;
  const float* g = gmod ? gmod + (size_t)b * 3 * W + 2 * W : nullptr;
  for (int i = threadIdx.x; i < W; i += blockDim.x) {
    const size_t j = (size_t)row * W + i;
    out[j] = from_f<T>(to_f(x[j]) + (g ? to_f(y[j]) * g[i] : to_f(y[j])));
  }
}

// The fused Q/K/V projection's output y [B*L, ncols] split into heads, Q and K rotated
// (rotate-half RoPE with cos/sin [B, L, hd/2]; cos null: no rotation, SigLIP):
//   q [B, nH, L, hd] (q null: skipped), k / v into [B, nKV, kv_len, hd] at sequence kv_off.
// Grid: B*L rows; the block's threads stride over the (head, rotation pair) of the row.
template <typename T>
__device__ void qkv_rope(const T* __restrict__ y, int ncols, T* __restrict__ q, T* __restrict__ k,
                         T* __restrict__ v, const T* __restrict__ cos_t, const T* __restrict__ sin_t,
                         int L, int nH, int nKV, int hd, int q_col, int k_col, int v_col, int kv_len,
                         int kv_off) {
  const int row = blockIdx.x, half = hd / 2;
  const int b = row / L, l = row % L;
  const T* yr = y + (size_t)row * ncols;
  const int pairs = (nH + 2 * nKV) * half;
  for (int p = threadIdx.x; p < pairs; p += blockDim.x) {
    const int head = p / half, i = p % half;
    T* dst;
    const T* src;
    bool rot = true;
    if (head < nH) {
      if (!q) continue;
      src = yr + q_col + head * hd;
      dst = q + (((size_t)b * nH + head) * L + l) * hd;
    } else if (head < nH + nKV) {
      const int h = head - nH;
      src = yr + k_col + h * hd;
      dst = k + (((size_t)b * nKV + h) * kv_len + kv_off + l) * hd;
    } else {
      const int h = head - nH - nKV;
      src = yr + v_col + h * hd;
      dst = v + (((size_t)b * nKV + h) * kv_len + kv_off + l) * hd;
      rot = false;
    }
    const float x1 = to_f(src[i]), x2 = to_f(src[i + half]);
    if (rot && cos_t) {
      const float c = to_f(cos_t[(size_t)row * half + i]), s = to_f(sin_t[(size_t)row * half + i]);
      dst[i] = from_f<T>(x1 * c - x2 * s);
      dst[i + half] = from_f<T>(x2 * c + x1 * s);
    } else {
      dst[i] = from_f<T>(x1);
      dst[i + half] = from_f<T>(x2);
    }
  }
}

__device__ __forceinline__ float gelu_tanh(float g) {
  return 0.5f * g * (1.f + tanhf(0.7978845608028654f * (g + 0.044715f * g * g * g)));
}

// h [rows, F] = gelu_tanh(y[:, :F]) * y[:, F:2F] (y [rows, 2F]); grid (column blocks, rows).
template <typename T>
__device__ void gelu_mul(const T* __restrict__ y, T* __restrict__ h, int F) {
  const size_t r = blockIdx.y;
  const T* yr = y + r * 2 * F;
  for (int c = blockIdx.x * blockDim.x + threadIdx.x; c < F; c += gridDim.x * blockDim.x)
    h[r * F + c] = from_f<T>(gelu_tanh(to_f(yr[c])) * to_f(yr[F + c]));
}

// out [rows, N] = act(y + bias) (+ residual): act 0 identity, 1 gelu_tanh; bias [N] and
// residual [rows, N] may be null. Grid (column blocks, rows).
template <typename T>
__device__ void bias_act(const T* __restrict__ y, const T* __restrict__ bias, const T* __restrict__ res,
                         T* __restrict__ out, int N, int act) {
  const size_t r = blockIdx.y;
  for (int c = blockIdx.x * blockDim.x + threadIdx.x; c < N; c += gridDim.x * blockDim.x) {
    float v = to_f(y[r * N + c]);
    if (bias) v = to_f(from_f<T>(v + to_f(bias[c])));
    if (act == 1) v = gelu_tanh(v);
    if (res) v = to_f(from_f<T>(v)) + to_f(res[r * N + c]);
    out[r * N + c] = from_f<T>(v);
  }
}

// Attention probabilities in place: s [R, n] (R = B * G * L rows of scores, G query-head groups
// per batch row) becomes softmax(s * scale + bias[b, 0, l or 0, :]) in f32, rounded to T.
// bias [B, 1, bl, n] f32 with bl = L or 1 (null: no mask). One block per row; the row lives in
// shared memory.
template <typename T>
__device__ void softmax_bias(T* __restrict__ s, const float* __restrict__ bias, int n, int L, int G, int bl,
                             float scale) {
  extern __shared__ float buf[];  // n floats, then 32 for the reductions
  float* red = buf + n;
  const int row = blockIdx.x, l = row % L, b = row / (L * G);
  T* sr = s + (size_t)row * n;
  const float* br = bias ? bias + ((size_t)b * bl + (bl == 1 ? 0 : l)) * n : nullptr;
  float m = -3.0e38f;
  for (int i = threadIdx.x; i < n; i += blockDim.x) {
    const float v = to_f(sr[i]) * scale + (bias ? br[i] : 0.f);
    buf[i] = v;
    m = fmaxf(m, v);
  }
  m = block_max(m, red);
  float sum = 0.f;
  for (int i = threadIdx.x; i < n; i += blockDim.x) {
    const float e = expf(buf[i] - m);
    buf[i] = e;
    sum += e;
  }
  sum = block_sum(sum, red);
  const float inv = 1.f / sum;
  for (int i = threadIdx.x; i < n; i += blockDim.x) sr[i] = from_f<T>(buf[i] * inv);
}


#define INSTANTIATE(T, S)                                                                              \
  extern "C" __global__ void add_norm_##S(const T* x, const T* y, const float* gmod, T* out_x1, T* out_h, \
                                          const float* alpha, const float* mod, int W, int rpb, float eps) { \
    add_norm<T>(x, y, gmod, out_x1, out_h, alpha, mod, W, rpb, eps);                                   \
  }                                                                                                    \
  extern "C" __global__ void gated_add_##S(const T* x, const T* y, const float* gmod, T* out, int W,     \
                                           int rpb) {                                                  \
    gated_add<T>(x, y, gmod, out, W, rpb);                                                             \
  }                                                                                                    \
  extern "C" __global__ void qkv_rope_##S(const T* y, int ncols, T* q, T* k, T* v, const T* c,          \
                                          const T* s, int L, int nH, int nKV, int hd, int qc, int kc,   \
                                          int vc, int kv_len, int kv_off) {                             \
    qkv_rope<T>(y, ncols, q, k, v, c, s, L, nH, nKV, hd, qc, kc, vc, kv_len, kv_off);                  \
  }                                                                                                    \
  extern "C" __global__ void gelu_mul_##S(const T* y, T* h, int F) { gelu_mul<T>(y, h, F); }            \
  extern "C" __global__ void bias_act_##S(const T* y, const T* b, const T* r, T* out, int N, int act) { \
    bias_act<T>(y, b, r, out, N, act);                                                                 \
  }                                                                                                    \
  extern "C" __global__ void softmax_bias_##S(T* s, const float* bias, int n, int L, int G, int bl,      \
                                              float scale) {                                           \
    softmax_bias<T>(s, bias, n, L, G, bl, scale);                                                      \
  }

INSTANTIATE(float, f32)
INSTANTIATE(__nv_bfloat16, bf16)
