// The C++ peer of tlsjax: the point-based TLS self-calibration written the way a bundle-
// adjustment engineer would write it on Ceres Solver (SPEC sections 1-3, 6).
//
//   * one AutoDiffCostFunction per observation of a target in a scan: 3 whitened residuals
//     wrap(F(X, EOP) + Delta(l; AP) - l) / sigma, parameter blocks target (3), scan pose (6:
//     Xs, Ys, Zs, omega, phi, kappa; x = R3(kappa) R2(phi) R1(omega) (X - S)) and APs (K);
//     the AP bases are evaluated at the observations (SPEC section 2);
//   * levelling pseudo-observations as compensator readings of the scan's pose,
//     omega_c = asin(g_y), phi_c = asin(-g_x / sqrt(1 - g_y^2)) with g = R e3 (as tlsjax);
//   * datum: Xs, Ys, Zs, kappa of the first scan held (all six without levelling); the APs do
//     not depend on the datum;
//   * DENSE_SCHUR with the targets in elimination group 0, Levenberg-Marquardt started with a
//     huge trust radius (its first steps are Gauss-Newton steps), function, parameter and
//     gradient tolerances 1e-10; the problem is built once and re-solved from new starts;
//   * the AP covariance from the Schur complement of the normal matrix at the solution (the
//     targets' 3 x 3 blocks eliminated, the reduced matrix inverted), times s0^2.
//
// Usage:
//   tlsjax_ceres_peer single PROBLEM.bin OUT.json [--repeats N] [--threads T]
//   tlsjax_ceres_peer mc PROBLEM.bin OUT.json [--threads T]
// The problem file is written by benchmarks/_ceres.py (layout documented there). "single"
// solves realisation 0 N times from the start (timing each solve with its covariance); "mc"
// solves every realisation once from the start, on T threads with one Problem each.

#include <ceres/ceres.h>

#include <Eigen/Dense>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kTwoPi = 2.0 * kPi;

// ---------------------------------------------------------------------------------------------
// Data

struct Data {
  int64_t n_scans = 0, n_targets = 0, n_obs = 0, n_aps = 0, architecture = 0, n_real = 0;
  double unit_length = 0.0, unit_length_2 = 0.0;
  std::vector<int64_t> ap_code, obs_scan, obs_target;
  std::vector<double> sigma, lev_sigma, start_targets, start_eops, start_aps;
  std::vector<double> observations, levelling;  // per realisation
};

template <typename V>
void read(std::ifstream& f, V& v, size_t n) {
  v.resize(n);
  f.read(reinterpret_cast<char*>(v.data()), n * sizeof(typename V::value_type));
  if (!f) throw std::runtime_error("problem file ends early");
}

Data load(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error("cannot open " + path);
  std::vector<int64_t> head;
  read(f, head, 7);
  if (head[0] != 0x7153A1) throw std::runtime_error("not a tlsjax peer problem file");
  Data d;
  d.n_scans = head[1], d.n_targets = head[2], d.n_obs = head[3], d.n_aps = head[4];
  d.architecture = head[5], d.n_real = head[6];
  std::vector<double> units;
  read(f, units, 2);
  d.unit_length = units[0], d.unit_length_2 = units[1];
  read(f, d.ap_code, d.n_aps);
  read(f, d.obs_scan, d.n_obs);
  read(f, d.obs_target, d.n_obs);
  read(f, d.sigma, 3 * d.n_obs);
  read(f, d.lev_sigma, 2 * d.n_scans);
  read(f, d.start_targets, 3 * d.n_targets);
  read(f, d.start_eops, 6 * d.n_scans);
  read(f, d.start_aps, d.n_aps);
  read(f, d.observations, 3 * d.n_obs * d.n_real);
  read(f, d.levelling, 2 * d.n_scans * d.n_real);
  return d;
}

// AP terms (SPEC section 3), in the order of benchmarks/_ceres.py AP_CODES: the group (0 range,
// 1 horizontal direction, 2 elevation angle) and the basis at an observation.
int ap_group(int64_t code) { return code <= 8 ? 0 : (code <= 21 ? 1 : 2); }

double ap_basis(int64_t code, double rho, double theta, double alpha, const Data& d) {
  const double U = d.unit_length, U2 = d.unit_length_2;
  switch (code) {
    case 0: return 1.0;                                   // A0
    case 1: return rho;                                   // A1
    case 2: return std::sin(alpha);                       // A2
    case 3: return std::sin(4 * kPi * rho / U);           // A3
    case 4: return std::cos(4 * kPi * rho / U);           // A4
    case 5: return std::sin(4 * kPi * rho / U2);          // A5
    case 6: return std::cos(4 * kPi * rho / U2);          // A6
    case 7: return std::sin(4 * theta);                   // A7
    case 8: return std::cos(4 * theta);                   // A8
    case 9: return theta;                                 // B1
    case 10: return std::sin(theta);                      // B2
    case 11: return std::cos(theta);                      // B3
    case 12: return std::sin(2 * theta);                  // B4
    case 13: return std::cos(2 * theta);                  // B5
    case 14: return 1.0 / std::cos(alpha) - (d.architecture == 0 ? 1.0 : 0.0);  // B6
    case 15: return std::tan(alpha);                      // B7
    case 16: return 1.0 / rho;                            // B8
    case 17: return std::sin(alpha);                      // B9
    case 18: return std::cos(alpha);                      // B10
    case 19: return std::sin(3 * alpha);                  // B11
    case 20: return std::sin(4 * alpha);                  // B12
    case 21: return 0.0;                                  // (unused)
    case 22: return 1.0;                                  // C0
    case 23: return alpha;                                // C1
    case 24: return std::sin(alpha);                      // C2
    case 25: return std::cos(alpha);                      // C3
    case 26: return std::sin(2 * alpha);                  // C4
    case 27: return std::cos(2 * alpha);                  // C5
    case 28: return 1.0 / rho;                            // C6
    case 29: return std::sin(theta);                      // C7
    case 30: return std::cos(theta);                      // C8
    case 31: return std::sin(3 * theta);                  // C9
    case 32: return std::cos(3 * theta);                  // C10
  }
  throw std::runtime_error("unknown AP code");
}

// ---------------------------------------------------------------------------------------------
// The model

inline double scalar(double x) { return x; }
template <typename T, int N>
inline double scalar(const ceres::Jet<T, N>& x) { return x.a; }

template <typename T>
inline T wrap(const T& a) {  // to (-pi, pi]
  return a - kTwoPi * std::ceil((scalar(a) - kPi) / kTwoPi);
}

template <typename T>
void rotation(const T* e, T R[3][3]) {  // R = R3(kappa) R2(phi) R1(omega), passive
  using std::cos, std::sin;
  const T cw = cos(e[3]), sw = sin(e[3]), cp = cos(e[4]), sp = sin(e[4]);
  const T ck = cos(e[5]), sk = sin(e[5]);
  const T r0[3] = {cp, sp * sw, -sp * cw}, r1[3] = {T(0.0), cw, sw};
  for (int j = 0; j < 3; ++j) {
    R[0][j] = ck * r0[j] + sk * r1[j];
    R[1][j] = -sk * r0[j] + ck * r1[j];
  }
  R[2][0] = sp, R[2][1] = -cp * sw, R[2][2] = cp * cw;
}

struct Observation {
  double l[3];      // observed range, horizontal direction, elevation angle
  double w[3];      // 1 / sigma
  double basis[3][40];  // AP bases of the observation per group (K <= 40)
  bool face2;
};

template <int K>
struct PointResidual {
  explicit PointResidual(const Observation* o) : o(o) {}
  template <typename T>
  bool operator()(const T* X, const T* e, const T* a, T* r) const {
    using std::atan2, std::sqrt;
    T R[3][3];
    rotation(e, R);
    const T d[3] = {X[0] - e[0], X[1] - e[1], X[2] - e[2]};
    T x[3];
    for (int i = 0; i < 3; ++i) x[i] = R[i][0] * d[0] + R[i][1] * d[1] + R[i][2] * d[2];
    const T rho = sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    T theta = atan2(x[1], x[0]);
    if (scalar(theta) < 0) theta += kTwoPi;
    T alpha = atan2(x[2], sqrt(x[0] * x[0] + x[1] * x[1]));
    if (o->face2) theta -= kPi, alpha = kPi - alpha;
    T delta[3] = {T(0.0), T(0.0), T(0.0)};
    for (int k = 0; k < K; ++k)
      for (int g = 0; g < 3; ++g) delta[g] += o->basis[g][k] * a[k];
    r[0] = (rho + delta[0] - o->l[0]) * o->w[0];
    r[1] = wrap(theta + delta[1] - o->l[1]) * o->w[1];
    r[2] = wrap(alpha + delta[2] - o->l[2]) * o->w[2];
    return true;
  }
  const Observation* o;
};

struct LevellingResidual {
  LevellingResidual(const double* reading, const double* w) : reading(reading), w(w) {}
  template <typename T>
  bool operator()(const T* e, T* r) const {
    using std::asin, std::sqrt;
    T R[3][3];
    rotation(e, R);
    const T gx = R[0][2], gy = R[1][2];
    r[0] = (asin(gy) - reading[0]) * w[0];
    r[1] = (asin(-gx / sqrt(1.0 - gy * gy)) - reading[1]) * w[1];
    return true;
  }
  const double* reading;
  const double* w;
};

template <int K>
ceres::CostFunction* point_cost(const Observation* o) {
  return new ceres::AutoDiffCostFunction<PointResidual<K>, 3, 3, 6, K>(new PointResidual<K>(o));
}

ceres::CostFunction* make_point_cost(int K, const Observation* o) {
  switch (K) {
#define CASE(k) \
  case k:       \
    return point_cost<k>(o);
    CASE(1) CASE(2) CASE(3) CASE(4) CASE(5) CASE(6) CASE(7) CASE(8) CASE(9) CASE(10)
    CASE(11) CASE(12) CASE(13) CASE(14) CASE(15) CASE(16) CASE(17) CASE(18) CASE(19) CASE(20)
    CASE(21) CASE(22) CASE(23) CASE(24) CASE(25) CASE(26) CASE(27) CASE(28) CASE(29) CASE(30)
    CASE(31) CASE(32)
#undef CASE
  }
  throw std::runtime_error("1 to 32 APs supported");
}

// ---------------------------------------------------------------------------------------------
// One problem, built once and re-solved

struct Result {
  std::vector<double> aps, cov;
  double s0sq = 0.0, seconds = 0.0;
  int iterations = 0, linear_solves = 0;
  bool converged = false;
};

class Peer {
 public:
  explicit Peer(const Data& d) : d_(d), obs_(d.n_obs) {
    targets_.resize(3 * d.n_targets);
    eops_.resize(6 * d.n_scans);
    aps_.resize(std::max<int64_t>(d.n_aps, 1));
    reading_.resize(2 * d.n_scans);
    lev_w_.resize(2 * d.n_scans);
    for (int64_t i = 0; i < d.n_obs; ++i)
      for (int g = 0; g < 3; ++g) obs_[i].w[g] = 1.0 / d.sigma[3 * i + g];
    bool levelled = false;
    for (int64_t j = 0; j < d.n_scans; ++j) {
      const bool lev = std::isfinite(d.lev_sigma[2 * j]);
      levelled |= lev;
      for (int c = 0; c < 2; ++c) lev_w_[2 * j + c] = lev ? 1.0 / d.lev_sigma[2 * j + c] : 0.0;
    }
    for (int64_t i = 0; i < d.n_obs; ++i) {
      point_costs_.push_back(make_point_cost(int(d.n_aps), &obs_[i]));
      problem_.AddResidualBlock(point_costs_.back(), nullptr, &targets_[3 * d.obs_target[i]],
                                &eops_[6 * d.obs_scan[i]], aps_.data());
    }
    for (int64_t j = 0; j < d.n_scans; ++j)
      if (lev_w_[2 * j] > 0) {
        lev_costs_.push_back(new ceres::AutoDiffCostFunction<LevellingResidual, 2, 6>(
            new LevellingResidual(&reading_[2 * j], &lev_w_[2 * j])));
        lev_scans_.push_back(int(j));
        problem_.AddResidualBlock(lev_costs_.back(), nullptr, &eops_[6 * j]);
      }
    held_ = levelled ? std::vector<int>{0, 1, 2, 5} : std::vector<int>{0, 1, 2, 3, 4, 5};
    if (levelled)
      problem_.SetManifold(&eops_[0], new ceres::SubsetManifold(6, held_));
    else
      problem_.SetParameterBlockConstant(&eops_[0]);
    auto* ordering = new ceres::ParameterBlockOrdering;
    for (int64_t t = 0; t < d.n_targets; ++t) ordering->AddElementToGroup(&targets_[3 * t], 0);
    for (int64_t j = 0; j < d.n_scans; ++j) ordering->AddElementToGroup(&eops_[6 * j], 1);
    ordering->AddElementToGroup(aps_.data(), 1);
    options_.linear_solver_ordering.reset(ordering);
    options_.linear_solver_type = ceres::DENSE_SCHUR;
    options_.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
    options_.initial_trust_region_radius = 1e16;
    options_.max_trust_region_radius = 1e32;
    options_.function_tolerance = 1e-10;
    options_.parameter_tolerance = 1e-10;
    options_.gradient_tolerance = 1e-10;
    options_.max_num_iterations = 100;
    options_.num_threads = 1;
    options_.logging_type = ceres::SILENT;
  }

  // Observations, levelling readings and the start of realisation k, then solve and the AP
  // covariance; the time of both.
  Result solve(int64_t k) {
    set_data(k);
    const auto t0 = std::chrono::steady_clock::now();
    ceres::Solver::Summary summary;
    ceres::Solve(options_, &problem_, &summary);
    Result res;
    covariance(&res, summary.final_cost);
    res.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    res.aps.assign(aps_.begin(), aps_.begin() + d_.n_aps);
    res.iterations = int(summary.iterations.size()) - 1;
    res.linear_solves = summary.num_linear_solves;
    res.converged = summary.termination_type == ceres::CONVERGENCE;
    return res;
  }

 private:
  void set_data(int64_t k) {
    const double* l = &d_.observations[3 * d_.n_obs * k];
    for (int64_t i = 0; i < d_.n_obs; ++i) {
      Observation& o = obs_[i];
      for (int g = 0; g < 3; ++g) o.l[g] = l[3 * i + g];
      o.face2 = d_.architecture == 1 && o.l[2] > kPi / 2;
      for (int g = 0; g < 3; ++g)
        for (int64_t a = 0; a < d_.n_aps; ++a) o.basis[g][a] = 0.0;
      for (int64_t a = 0; a < d_.n_aps; ++a)
        o.basis[ap_group(d_.ap_code[a])][a] = ap_basis(d_.ap_code[a], o.l[0], o.l[1], o.l[2], d_);
    }
    const double* lev = &d_.levelling[2 * d_.n_scans * k];
    std::copy(lev, lev + 2 * d_.n_scans, reading_.begin());
    targets_ = d_.start_targets;
    eops_ = d_.start_eops;
    std::copy(d_.start_aps.begin(), d_.start_aps.end(), aps_.begin());
  }

  // Normal matrix at the solution from each residual block's Jacobians, the targets
  // eliminated by their 3 x 3 blocks (Schur complement), the reduced matrix of the free pose
  // parameters and APs inverted; its AP block times s0^2.
  void covariance(Result* res, double final_cost) {
    using RowMat = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
    const int S = int(d_.n_scans), K = int(d_.n_aps), r = 6 * S + K;
    Eigen::MatrixXd Nzz = Eigen::MatrixXd::Zero(r, r);
    std::vector<Eigen::Matrix3d> Ntt(d_.n_targets, Eigen::Matrix3d::Zero());
    std::vector<Eigen::MatrixXd> Ntz(d_.n_targets, Eigen::MatrixXd::Zero(3, r));
    std::vector<double> Jt(9), Js(18), Ja(3 * std::max(K, 1)), res3(3);
    for (int64_t i = 0; i < d_.n_obs; ++i) {
      const int t = int(d_.obs_target[i]), s = int(d_.obs_scan[i]);
      const double* params[3] = {&targets_[3 * t], &eops_[6 * s], aps_.data()};
      double* jac[3] = {Jt.data(), Js.data(), Ja.data()};
      point_costs_[i]->Evaluate(params, res3.data(), jac);
      const Eigen::Map<Eigen::Matrix<double, 3, 3, Eigen::RowMajor>> A(Jt.data());
      const Eigen::Map<Eigen::Matrix<double, 3, 6, Eigen::RowMajor>> P(Js.data());
      const Eigen::Map<RowMat> G(Ja.data(), 3, K);
      Ntt[t] += A.transpose() * A;
      Ntz[t].middleCols(6 * s, 6) += A.transpose() * P;
      Ntz[t].rightCols(K) += A.transpose() * G;
      Nzz.block(6 * s, 6 * s, 6, 6) += P.transpose() * P;
      Nzz.block(6 * s, 6 * S, 6, K) += P.transpose() * G;
      Nzz.bottomRightCorner(K, K) += G.transpose() * G;
    }
    Nzz.bottomLeftCorner(K, 6 * S) = Nzz.topRightCorner(6 * S, K).transpose();
    for (size_t q = 0; q < lev_costs_.size(); ++q) {
      const int j = lev_scans_[q];
      double J[12], rr[2];
      const double* params[1] = {&eops_[6 * j]};
      double* jac[1] = {J};
      lev_costs_[q]->Evaluate(params, rr, jac);
      const Eigen::Map<Eigen::Matrix<double, 2, 6, Eigen::RowMajor>> L(J);
      Nzz.block(6 * j, 6 * j, 6, 6) += L.transpose() * L;
    }
    for (int64_t t = 0; t < d_.n_targets; ++t)
      Nzz.noalias() -= Ntz[t].transpose() * Ntt[t].ldlt().solve(Ntz[t]);
    std::vector<int> free;
    for (int c = 0; c < r; ++c)
      if (!(c < 6 && std::find(held_.begin(), held_.end(), c) != held_.end())) free.push_back(c);
    const int nf = int(free.size());
    Eigen::MatrixXd Kf(nf, nf);
    for (int a = 0; a < nf; ++a)
      for (int b = 0; b < nf; ++b) Kf(a, b) = Nzz(free[a], free[b]);
    const Eigen::MatrixXd Q = Kf.llt().solve(Eigen::MatrixXd::Identity(nf, nf));
    const double dof = 3.0 * d_.n_obs + 2.0 * lev_costs_.size() - (3.0 * d_.n_targets + nf);
    res->s0sq = 2.0 * final_cost / dof;
    res->cov.resize(size_t(K) * K);
    for (int a = 0; a < K; ++a)
      for (int b = 0; b < K; ++b) res->cov[a * K + b] = Q(nf - K + a, nf - K + b) * res->s0sq;
  }

  const Data& d_;
  std::vector<Observation> obs_;
  std::vector<double> targets_, eops_, aps_, reading_, lev_w_;
  std::vector<int> held_, lev_scans_;
  std::vector<ceres::CostFunction*> point_costs_, lev_costs_;  // owned by problem_
  ceres::Problem problem_;
  ceres::Solver::Options options_;
};

void write_json(const std::string& path, const std::vector<Result>& results,
                const std::vector<double>& wall, int threads) {
  std::ofstream f(path);
  f.precision(17);
  f << "{\"threads\": " << threads << ", \"wall_s\": [";
  for (size_t i = 0; i < wall.size(); ++i) f << (i ? ", " : "") << wall[i];
  f << "], \"results\": [";
  for (size_t i = 0; i < results.size(); ++i) {
    const Result& r = results[i];
    f << (i ? ",\n" : "") << "{\"seconds\": " << r.seconds << ", \"iterations\": " << r.iterations
      << ", \"linear_solves\": " << r.linear_solves << ", \"converged\": " << r.converged
      << ", \"s0sq\": " << r.s0sq << ", \"aps\": [";
    for (size_t k = 0; k < r.aps.size(); ++k) f << (k ? ", " : "") << r.aps[k];
    f << "], \"ap_covariance\": [";
    for (size_t k = 0; k < r.cov.size(); ++k) f << (k ? ", " : "") << r.cov[k];
    f << "]}";
  }
  f << "]}\n";
}

}  // namespace

int main(int argc, char** argv) {
  try {
    if (argc < 4) {
      std::cerr << "usage: tlsjax_ceres_peer single|mc PROBLEM.bin OUT.json [--repeats N] "
                   "[--threads T]\n";
      return 2;
    }
    const std::string mode = argv[1];
    int repeats = 1, threads = 1;
    for (int i = 4; i + 1 < argc; i += 2) {
      const std::string opt = argv[i];
      if (opt == "--repeats") repeats = std::stoi(argv[i + 1]);
      if (opt == "--threads") threads = std::stoi(argv[i + 1]);
    }
    const Data d = load(argv[2]);
    std::vector<Result> results;
    std::vector<double> wall;
    if (mode == "single") {
      Peer peer(d);
      for (int k = 0; k < repeats; ++k) {
        results.push_back(peer.solve(0));
        wall.push_back(results.back().seconds);
      }
    } else if (mode == "mc") {
      results.resize(d.n_real);
      std::vector<std::unique_ptr<Peer>> peers;
      for (int t = 0; t < threads; ++t) peers.emplace_back(new Peer(d));  // built once
      std::atomic<int64_t> next(0);
      const auto t0 = std::chrono::steady_clock::now();
      std::vector<std::thread> pool;
      for (int t = 0; t < threads; ++t)
        pool.emplace_back([&, t] {
          for (int64_t k; (k = next++) < d.n_real;) results[k] = peers[t]->solve(k);
        });
      for (auto& th : pool) th.join();
      wall.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    } else {
      throw std::runtime_error("mode must be single or mc");
    }
    write_json(argv[3], results, wall, threads);
  } catch (const std::exception& e) {
    std::cerr << "tlsjax_ceres_peer: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
