// C++/Eigen reference for jaximu's Euler preintegration (Forster et al.; GTSAM's
// ManifoldPreintegration): the same mathematics as
// jaximu.preintegrate(gyro, accel, dt, bias, noise, scheme="euler"), in double precision
// with fixed-size Eigen matrices, one core, timed with a steady clock.
//
// Per sample k (raw ω̃, f̃, step h; linearisation bias b_g, b_a):
//
//   ω = ω̃ - b_g,  f = f̃ - b_a,  φ = ω h,  R = ΔR (before the step)
//   Δp += Δv h + ½ R f h²,   Δv += R f h,   ΔR ← ΔR Exp(φ)   (exact exponential)
//
// Error [δθ, δp, δv] (ΔR = ΔR̂ Exp(δθ); δp, δv additive in the first frame), one-step
// transition and noise Jacobian (noise [n_g, n_a], Q_c = diag(σ_g², σ_a²) / h per axis):
//
//   F = [[A, 0, 0], [Cp, I, h I], [Cv, 0, I]],   G = [[B, 0], [0, Ep], [0, Ev]]
//   A = Exp(φ)ᵀ,  B = -Jr(φ) h,  Cv = -R [f]x h,  Cp = -½ R [f]x h²,  Ev = -R h,  Ep = -½ R h²
//   P ← F P Fᵀ + G Q_c Gᵀ
//
// and the bias Jacobians (the bias columns of the accumulated transition):
//
//   dp/dbg ← dp/dbg + h dv/dbg + Cp dR/dbg,   dp/dba ← dp/dba + h dv/dba + Ep
//   dv/dbg ← dv/dbg + Cv dR/dbg,              dv/dba ← dv/dba + Ev
//   dR/dbg ← A dR/dbg + B
//
// Two covariance kernels, same numbers to rounding:
//   "blocked": the six upper 3×3 blocks of P, using the zero/identity blocks of F;
//   "dense":   the textbook dense update with a 9×9 F and a 9×6 G.
//
// A third, the peer itself, when compiled with -DJAXIMU_WITH_BASALT and Basalt's headers
// (basalt-headers' include/ and its thirdparty/Sophus on the include path):
//   "basalt":  basalt::IntegratedImuMeasurement<double>::integrate, sample by sample, as
//              Basalt's VIO calls it (discrete noise variances σ²/h; timestamps in ns).
//              Basalt rotates the step's specific force by the half-step rotation
//              ΔR Exp(φ/2), not by ΔR, so its deltas differ from the Euler ones by O(|ω| h)
//              relative; its error is [δp, δθ, δv] with the rotation error on the left
//              (ΔR = Exp(δθ) ΔR̂). The dump converts it to this program's layout
//              ([δθ, δp, δv], right error δθ_r = ΔRᵀ δθ_l) so the fields line up.
//
// Usage: preintegrate_reference INPUT [--min-time S] [--kernels blocked,dense[,basalt]]
//                               [--dump PREFIX]
//
// INPUT (little-endian binary): 8 bytes "JXPI0001", int64 N (windows), int64 L (samples per
// window), 12 doubles b_g[3], b_a[3], σ_g[3] (rad/s/√Hz), σ_a[3] (m/s²/√Hz), then N·L rows
// of 7 doubles (gx gy gz ax ay az dt), window after window.
//
// Every window starts from the identity. Each kernel is run over all N windows, repeatedly
// until at least 3 runs and S seconds (default 0.3); the best run is reported. stdout: one
// JSON object with the timings and the result of window 0. With --dump, PREFIX_<kernel>.bin
// holds every window's result, 137 doubles each: t, q (w x y z), Δv, Δp, cov (9×9), dR/dbg,
// dp/dbg, dp/dba, dv/dbg, dv/dba (3×3 each); matrices row-major.

#ifdef JAXIMU_WITH_BASALT
#include <basalt/imu/preintegration.h>
#endif

#include <Eigen/Core>
#include <Eigen/Geometry>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

namespace {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using Mat9 = Eigen::Matrix<double, 9, 9>;
using Mat96 = Eigen::Matrix<double, 9, 6>;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using Quat = Eigen::Quaterniond;

constexpr int kRow = 7;        // gx gy gz ax ay az dt
constexpr int kOutSize = 137;  // doubles per window in the dump
#ifdef JAXIMU_WITH_BASALT
const std::string kBasaltName = ", basalt";
#else
const std::string kBasaltName = "";  // built without Basalt's headers
#endif

struct Noise {
  Vec3 var_g;  // σ_g² per axis
  Vec3 var_a;  // σ_a² per axis
};

struct Result {
  double t = 0.0;
  Quat q = Quat::Identity();
  Vec3 dv = Vec3::Zero();
  Vec3 dp = Vec3::Zero();
  Mat9 cov = Mat9::Zero();
  Mat3 dR_dbg = Mat3::Zero();
  Mat3 dp_dbg = Mat3::Zero();
  Mat3 dp_dba = Mat3::Zero();
  Mat3 dv_dbg = Mat3::Zero();
  Mat3 dv_dba = Mat3::Zero();
};

inline Mat3 skew(const Vec3& v) {
  Mat3 S;
  S << 0.0, -v.z(), v.y(),
       v.z(), 0.0, -v.x(),
       -v.y(), v.x(), 0.0;
  return S;
}

// SO(3) exponential of φ as the unit quaternion [cos(θ/2), sin(θ/2) φ/θ], its matrix
// transposed (A = Exp(φ)ᵀ) and the right Jacobian Jr(φ) = I - a[φ]x + b[φ]x², with
// a = (1 - cos θ)/θ², b = (θ - sin θ)/θ³. Taylor series to θ⁶ below θ² = 1e-4.
struct So3Step {
  Quat dq;
  Mat3 A;
  Mat3 Jr;
};

inline So3Step so3_step(const Vec3& phi) {
  const double t2 = phi.squaredNorm();
  double c, k, b;  // quaternion [c, k φ]; a = 2 k², sin θ / θ = 2 c k
  if (t2 < 1e-4) {
    const double t4 = t2 * t2, t6 = t4 * t2;
    c = 1.0 - t2 / 8.0 + t4 / 384.0 - t6 / 46080.0;
    k = 0.5 - t2 / 48.0 + t4 / 3840.0 - t6 / 645120.0;
    b = 1.0 / 6.0 - t2 / 120.0 + t4 / 5040.0 - t6 / 362880.0;
  } else {
    const double th = std::sqrt(t2);
    c = std::cos(0.5 * th);
    k = std::sin(0.5 * th) / th;
    b = (th - std::sin(th)) / (t2 * th);
  }
  const double a = 2.0 * k * k;
  const double s = 2.0 * c * k;
  So3Step out;
  out.dq = Quat(c, k * phi.x(), k * phi.y(), k * phi.z());
  const Mat3 K = skew(phi);
  const Mat3 K2 = phi * phi.transpose() - t2 * Mat3::Identity();  // [φ]x²
  out.A = Mat3::Identity() - s * K + a * K2;                      // Exp(φ)ᵀ = Exp(-φ)
  out.Jr = Mat3::Identity() - a * K + b * K2;
  return out;
}

// One window of L samples. Dense = false: block-structured covariance update.
template <bool Dense>
void preintegrate(const double* rows, int64_t L, const Vec3& b_g, const Vec3& b_a,
                  const Noise& noise, Result& out) {
  double t = 0.0;
  Quat q = Quat::Identity();
  Vec3 dv = Vec3::Zero(), dp = Vec3::Zero();
  Mat3 JRg = Mat3::Zero(), Jpg = Mat3::Zero(), Jpa = Mat3::Zero(), Jvg = Mat3::Zero(),
       Jva = Mat3::Zero();
  // covariance: upper blocks (blocked) or the full matrix (dense)
  Mat3 P00 = Mat3::Zero(), P01 = Mat3::Zero(), P02 = Mat3::Zero(), P11 = Mat3::Zero(),
       P12 = Mat3::Zero(), P22 = Mat3::Zero();
  Mat9 P = Mat9::Zero();

  for (int64_t k = 0; k < L; ++k) {
    const double* r = rows + kRow * k;
    const Vec3 w = Vec3(r[0], r[1], r[2]) - b_g;
    const Vec3 f = Vec3(r[3], r[4], r[5]) - b_a;
    const double h = r[6];
    const double h2 = h * h, hh2 = 0.5 * h2;

    const Mat3 R = q.toRotationMatrix();
    const So3Step e = so3_step(w * h);
    const Vec3 u = R * f;
    const Mat3 Rf = R * skew(f);
    const Mat3 Cv = -h * Rf;
    const Mat3 Cp = -hh2 * Rf;
    const Mat3 B = -h * e.Jr;

    // covariance (F and G of the step at the current ΔR)
    const Vec3 sg = noise.var_g / h, sa = noise.var_a / h;  // Q_c = diag(σ²) / h
    if constexpr (Dense) {
      Mat9 F = Mat9::Identity();
      F.block<3, 3>(0, 0) = e.A;
      F.block<3, 3>(3, 0) = Cp;
      F.block<3, 3>(3, 6) = h * Mat3::Identity();
      F.block<3, 3>(6, 0) = Cv;
      Mat96 G = Mat96::Zero();
      G.block<3, 3>(0, 0) = B;
      G.block<3, 3>(3, 3) = -hh2 * R;
      G.block<3, 3>(6, 3) = -h * R;
      Vec6 qc;
      qc.head<3>() = sg;
      qc.tail<3>() = sa;
      P = F * P * F.transpose() + G * qc.asDiagonal() * G.transpose();
    } else {
      // M = F P (rows θ, p, v; the M21 block is not needed for the upper blocks of F P Fᵀ)
      const Mat3 M00 = e.A * P00, M01 = e.A * P01, M02 = e.A * P02;
      const Mat3 M10 = P01.transpose() + h * P02.transpose() + Cp * P00;
      const Mat3 M11 = P11 + h * P12.transpose() + Cp * P01;
      const Mat3 M12 = P12 + h * P22 + Cp * P02;
      const Mat3 M20 = P02.transpose() + Cv * P00;
      const Mat3 M22 = P22 + Cv * P02;
      // noise: B diag(sg) Bᵀ on θθ; R diag(sa) Rᵀ scaled by (¼h⁴, ½h³, h²) on pp, pv, vv
      const Mat3 Qg = B * sg.asDiagonal() * B.transpose();
      const Mat3 Qa = R * sa.asDiagonal() * R.transpose();
      // F P Fᵀ: column blocks of Fᵀ are [Aᵀ; 0; 0], [Cpᵀ; I; h I], [Cvᵀ; 0; I]
      const Mat3 N00 = M00 * e.A.transpose() + Qg;
      const Mat3 N11 = M10 * Cp.transpose() + M11 + h * M12 + (0.25 * h2 * h2) * Qa;
      const Mat3 N22 = M20 * Cv.transpose() + M22 + h2 * Qa;
      P01 = M00 * Cp.transpose() + M01 + h * M02;
      P02 = M00 * Cv.transpose() + M02;
      P12 = M10 * Cv.transpose() + M12 + (0.5 * h2 * h) * Qa;
      P00 = 0.5 * (N00 + N00.transpose());
      P11 = 0.5 * (N11 + N11.transpose());
      P22 = 0.5 * (N22 + N22.transpose());
    }

    // bias Jacobians (old values on the right-hand sides)
    Jpg += h * Jvg + Cp * JRg;
    Jpa += h * Jva - hh2 * R;
    Jvg += Cv * JRg;
    Jva -= h * R;
    JRg = e.A * JRg + B;

    // mean
    dp += h * dv + hh2 * u;
    dv += h * u;
    q = (q * e.dq).normalized();
    t += h;
  }

  out.t = t;
  out.q = q;
  out.dv = dv;
  out.dp = dp;
  if constexpr (Dense) {
    out.cov = P;
  } else {
    out.cov.block<3, 3>(0, 0) = P00;
    out.cov.block<3, 3>(0, 3) = P01;
    out.cov.block<3, 3>(0, 6) = P02;
    out.cov.block<3, 3>(3, 0) = P01.transpose();
    out.cov.block<3, 3>(3, 3) = P11;
    out.cov.block<3, 3>(3, 6) = P12;
    out.cov.block<3, 3>(6, 0) = P02.transpose();
    out.cov.block<3, 3>(6, 3) = P12.transpose();
    out.cov.block<3, 3>(6, 6) = P22;
  }
  out.dR_dbg = JRg;
  out.dp_dbg = Jpg;
  out.dp_dba = Jpa;
  out.dv_dbg = Jvg;
  out.dv_dba = Jva;
}

#ifdef JAXIMU_WITH_BASALT
// Basalt's own integration of one window (see the header comment), converted to Result.
void basalt_window(const double* rows, int64_t L, const Vec3& b_g, const Vec3& b_a,
                   const Noise& noise, Result& out) {
  basalt::IntegratedImuMeasurement<double> imu(0, b_g, b_a);
  basalt::ImuData<double> d;
  int64_t t_ns = 0;
  for (int64_t k = 0; k < L; ++k) {
    const double* r = rows + k * kRow;
    const double h = r[6];
    t_ns += static_cast<int64_t>(std::llround(h * 1e9));
    d.t_ns = t_ns;
    d.gyro = Vec3(r[0], r[1], r[2]);
    d.accel = Vec3(r[3], r[4], r[5]);
    imu.integrate(d, noise.var_a / h, noise.var_g / h);  // Basalt's discrete σ²/h
  }
  const auto& s = imu.getDeltaState();
  const Mat3 R = s.T_w_i.so3().matrix();
  // Basalt [δp, δθ_l, δv] to [δθ_r, δp, δv]: T = [[0, Rᵀ, 0], [I, 0, 0], [0, 0, I]]
  Mat9 T = Mat9::Zero();
  T.block<3, 3>(0, 3) = R.transpose();
  T.block<3, 3>(3, 0).setIdentity();
  T.block<3, 3>(6, 6).setIdentity();
  out.t = static_cast<double>(s.t_ns) * 1e-9;
  out.q = Quat(s.T_w_i.so3().unit_quaternion());
  out.dv = s.vel_w_i;
  out.dp = s.T_w_i.translation();
  out.cov = T * imu.get_cov() * T.transpose();
  const Eigen::Matrix<double, 9, 3> Jg = T * imu.get_d_state_d_bg();
  const Eigen::Matrix<double, 9, 3> Ja = T * imu.get_d_state_d_ba();
  out.dR_dbg = Jg.block<3, 3>(0, 0);
  out.dp_dbg = Jg.block<3, 3>(3, 0);
  out.dv_dbg = Jg.block<3, 3>(6, 0);
  out.dp_dba = Ja.block<3, 3>(3, 0);
  out.dv_dba = Ja.block<3, 3>(6, 0);
}
#endif

struct Input {
  int64_t n = 0, len = 0;
  Vec3 b_g, b_a;
  Noise noise;
  std::vector<double> rows;
};

[[noreturn]] void fail(const std::string& msg) {
  std::fprintf(stderr, "preintegrate_reference: %s\n", msg.c_str());
  std::exit(2);
}

Input read_input(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) fail("cannot open " + path);
  char magic[8];
  in.read(magic, 8);
  if (!in || std::memcmp(magic, "JXPI0001", 8) != 0) fail(path + ": not a JXPI0001 file");
  Input x;
  int64_t dims[2];
  double hdr[12];
  in.read(reinterpret_cast<char*>(dims), sizeof dims);
  in.read(reinterpret_cast<char*>(hdr), sizeof hdr);
  if (!in) fail(path + ": truncated header");
  x.n = dims[0];
  x.len = dims[1];
  if (x.n < 1 || x.len < 1) fail(path + ": N and L must be positive");
  x.b_g = Vec3(hdr[0], hdr[1], hdr[2]);
  x.b_a = Vec3(hdr[3], hdr[4], hdr[5]);
  x.noise.var_g = Vec3(hdr[6], hdr[7], hdr[8]).cwiseAbs2();
  x.noise.var_a = Vec3(hdr[9], hdr[10], hdr[11]).cwiseAbs2();
  const size_t count = static_cast<size_t>(x.n) * static_cast<size_t>(x.len) * kRow;
  x.rows.resize(count);
  in.read(reinterpret_cast<char*>(x.rows.data()), static_cast<std::streamsize>(count * 8));
  if (!in) fail(path + ": truncated samples");
  for (int64_t i = 0; i < x.n * x.len; ++i) {
    const double h = x.rows[static_cast<size_t>(i) * kRow + 6];
    if (!(h > 0.0) || !std::isfinite(h)) fail(path + ": dt must be positive and finite");
  }
  return x;
}

void flatten(const Result& r, double* o) {
  auto put3 = [&](const Mat3& m) {
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) *o++ = m(i, j);
  };
  *o++ = r.t;
  *o++ = r.q.w();
  *o++ = r.q.x();
  *o++ = r.q.y();
  *o++ = r.q.z();
  for (int i = 0; i < 3; ++i) *o++ = r.dv(i);
  for (int i = 0; i < 3; ++i) *o++ = r.dp(i);
  for (int i = 0; i < 9; ++i)
    for (int j = 0; j < 9; ++j) *o++ = r.cov(i, j);
  put3(r.dR_dbg);
  put3(r.dp_dbg);
  put3(r.dp_dba);
  put3(r.dv_dbg);
  put3(r.dv_dba);
}

std::string json_array(const double* x, int n) {
  std::ostringstream s;
  s << '[';
  char buf[32];
  for (int i = 0; i < n; ++i) {
    std::snprintf(buf, sizeof buf, "%.17g", x[i]);
    s << (i ? ", " : "") << buf;
  }
  s << ']';
  return s.str();
}

std::string json_result(const Result& r) {
  double o[kOutSize];
  flatten(r, o);
  std::ostringstream s;
  char t[32];
  std::snprintf(t, sizeof t, "%.17g", o[0]);
  s << "{\"delta_t\": " << t << ", \"delta_q\": " << json_array(o + 1, 4)
    << ", \"delta_v\": " << json_array(o + 5, 3) << ", \"delta_p\": " << json_array(o + 8, 3)
    << ", \"cov\": " << json_array(o + 11, 81)
    << ", \"dR_dbg\": " << json_array(o + 92, 9) << ", \"dp_dbg\": " << json_array(o + 101, 9)
    << ", \"dp_dba\": " << json_array(o + 110, 9) << ", \"dv_dbg\": " << json_array(o + 119, 9)
    << ", \"dv_dba\": " << json_array(o + 128, 9) << '}';
  return s.str();
}

using Kernel = void (*)(const double*, int64_t, const Vec3&, const Vec3&, const Noise&, Result&);

struct Timing {
  double best_s = std::numeric_limits<double>::infinity();
  double total_s = 0.0;
  int reps = 0;
};

Timing run_kernel(Kernel kernel, const Input& x, std::vector<Result>& out, double min_time) {
  using clock = std::chrono::steady_clock;
  Timing tm;
  const int64_t stride = x.len * kRow;
  while (tm.reps < 3 || tm.total_s < min_time) {
    const auto t0 = clock::now();
    for (int64_t w = 0; w < x.n; ++w)
      kernel(x.rows.data() + w * stride, x.len, x.b_g, x.b_a, x.noise, out[w]);
    const double s = std::chrono::duration<double>(clock::now() - t0).count();
    tm.best_s = std::min(tm.best_s, s);
    tm.total_s += s;
    ++tm.reps;
    if (tm.reps >= 10000) break;
  }
  return tm;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr,
                 "usage: %s INPUT [--min-time S] [--kernels blocked,dense[,basalt]] [--dump PREFIX]\n",
                 argv[0]);
    return 2;
  }
  std::string input_path = argv[1], dump, kernels = "blocked,dense";
  double min_time = 0.3;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    if (i + 1 >= argc) fail("option " + a + " needs a value");
    if (a == "--min-time") {
      min_time = std::atof(argv[++i]);
    } else if (a == "--kernels") {
      kernels = argv[++i];
    } else if (a == "--dump") {
      dump = argv[++i];
    } else {
      fail("unknown option " + a);
    }
  }
  const Input x = read_input(input_path);
  const double samples = static_cast<double>(x.n) * static_cast<double>(x.len);

  std::ostringstream js;
  js << "{\"windows\": " << x.n << ", \"window_len\": " << x.len << ", \"samples\": "
     << x.n * x.len << ", \"compiler\": \"" << __VERSION__ << "\", \"eigen\": \""
     << EIGEN_WORLD_VERSION << '.' << EIGEN_MAJOR_VERSION << '.' << EIGEN_MINOR_VERSION
     << "\", \"kernels\": {";
  std::stringstream names(kernels);
  std::string name;
  bool first = true;
  while (std::getline(names, name, ',')) {
    Kernel kernel = nullptr;
    if (name == "blocked") kernel = preintegrate<false>;
    else if (name == "dense") kernel = preintegrate<true>;
#ifdef JAXIMU_WITH_BASALT
    else if (name == "basalt") kernel = basalt_window;
#endif
    else fail("unknown kernel " + name + " (blocked, dense" + kBasaltName + ")");
    std::vector<Result> out(static_cast<size_t>(x.n));
    const Timing tm = run_kernel(kernel, x, out, min_time);
    char buf[256];
    std::snprintf(buf, sizeof buf,
                  "\"best_s\": %.9g, \"total_s\": %.9g, \"reps\": %d, \"us_per_sample\": %.6g, "
                  "\"samples_per_s\": %.6g",
                  tm.best_s, tm.total_s, tm.reps, tm.best_s / samples * 1e6,
                  samples / tm.best_s);
    js << (first ? "" : ", ") << '"' << name << "\": {" << buf
       << ", \"first\": " << json_result(out[0]) << '}';
    first = false;
    if (!dump.empty()) {
      std::vector<double> flat(out.size() * kOutSize);
      for (size_t w = 0; w < out.size(); ++w) flatten(out[w], flat.data() + w * kOutSize);
      const std::string path = dump + "_" + name + ".bin";
      std::ofstream o(path, std::ios::binary);
      o.write(reinterpret_cast<const char*>(flat.data()),
              static_cast<std::streamsize>(flat.size() * sizeof(double)));
      if (!o) fail("cannot write " + path);
    }
  }
  js << "}}";
  std::printf("%s\n", js.str().c_str());
  return 0;
}
