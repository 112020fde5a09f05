// Runs slamkit/csrc/slk_vec16.h's operations on fixed inputs and prints each result lane by lane,
// one "name: values" line each, as hexadecimal floats (exact; tests/e2e/test_native_variants.py
// compares them with numpy).
#include <cstdio>

#include "slk_vec16.h"

namespace {

void print(const char* name, const vf& v) {
  std::printf("%s:", name);
  for (int i = 0; i < 16; ++i) std::printf(" %a", (double)v[i]);
  std::printf("\n");
}
void print(const char* name, const vi& v) {
  std::printf("%s:", name);
  for (int i = 0; i < 16; ++i) std::printf(" %a", (double)v[i]);
  std::printf("\n");
}
void print(const char* name, const vd& v) {
  std::printf("%s:", name);
  for (int i = 0; i < 8; ++i) std::printf(" %a", v[i]);
  std::printf("\n");
}
void print(const char* name, double x) { std::printf("%s: %a\n", name, x); }

}  // namespace

int main() {
  float a_in[16], b_in[16];
  double d_in[8];
  for (int i = 0; i < 16; ++i) {
    a_in[i] = 0.37f * (float)(i - 7) + 0.011f * (float)(i * i);  // negative and positive, not integers
    b_in[i] = 1.5f + 0.25f * (float)((i * 5) % 16);
  }
  for (int i = 0; i < 8; ++i) d_in[i] = 1e8 * (i % 2 ? 1.0 : -1.0) + 0.1 * (double)i;
  const vf a = loadu(a_in), b = loadu(b_in);
  print("a", a);
  print("b", b);
  print("lane", LANE);
  print("add", a + b);
  print("sub_scalar", 2.0f - a);
  print("mul", a * b);
  print("div_scalar", a / 3.0f);
  print("neg", -a);
  print("lt", a < b);
  print("ge_scalar", a >= 0.0f);
  print("select", select(a < 0.0f, b, a));
  print("to_vi", to_vi(a * 4.0f));
  print("to_vf", to_vf(LANE + LANE + LANE - 20));
  print("bits", as_vi(a) & vi1(0x7fffffff));
  print("shift", (LANE + 1) << 3);
  print("sqrt", vsqrt(b));
  print("fma", vfma(a, b, vf1(0.5f)));
  print("hsum", (double)hsum(a));
  print("any_none", (double)any(a > 100.0f));
  print("any_one", (double)any(LANE == 15));
  print("all_but_one", (double)all(LANE < 15));
  print("all", (double)all(LANE >= 0));
  vd lo, hi;
  widen(a, lo, hi);
  print("widen_lo", lo);
  print("widen_hi", hi);
  print("narrow", narrow(hi, lo));
  print("ld8", ld8(a_in + 4));
  float st_out[16] = {0};
  st8(st_out + 3, loadu(d_in) * vd1(1e-8));
  print("st8", loadu(st_out));
  print("dsum", hsum(loadu(d_in)));
  vf blocks = a;
  for (int h = 0; h < HALVES; ++h) block(blocks, h) = block(blocks, h) * block_of(2.0f) + to_vf(block_lanes());
  print("blocks", blocks);
  print("lane_bits", (double)lane_bits((LANE == 0) | (LANE == 9) | (LANE == 15)));
  // a select per block (the kernels' loops), of floats and of integers
  vf picked = a, from_b = b, from_a = a;
  vi picked_int = LANE, doubled = LANE + LANE, lanes = LANE, negative = a < 0.0f;
  for (int h = 0; h < HALVES; ++h) {
    block(picked, h) = select(block(negative, h), block(from_b, h), block(from_a, h));
    block(picked_int, h) = select(block(negative, h), block(doubled, h), block(lanes, h));
  }
  print("block_select", picked);
  print("block_select_int", picked_int);
  return 0;
}
