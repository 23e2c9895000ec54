// The segmentation driver: calibration, the streamed classification and
// clean-up pass, component resolution, the output pass; file outputs.
#include "libmodel/segment/segment.h"

#include "libmodel/format/atomic.h"
#include "libmodel/provenance.h"
#include "libmodel/segment/detail.h"

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>

namespace orthosim {

using namespace segment_detail;

// ---- options -------------------------------------------------------------------

const char* to_string(SegmentOptions::Normalise n) {
  switch (n) {
    case SegmentOptions::Normalise::none: return "none";
    case SegmentOptions::Normalise::gain: return "gain";
    case SegmentOptions::Normalise::plane: return "plane";
  }
  return "?";
}

const char* to_string(SegmentOptions::Classify c) {
  switch (c) {
    case SegmentOptions::Classify::nearest: return "nearest";
    case SegmentOptions::Classify::mahalanobis: return "mahalanobis";
  }
  return "?";
}

const char* to_string(SegmentOptions::Space s) {
  switch (s) {
    case SegmentOptions::Space::cielab: return "cielab";
    case SegmentOptions::Space::rgb: return "rgb";
  }
  return "?";
}

std::vector<int> nearest_table_labels(const std::vector<Prototype>& prototypes) {
  auto d2 = [](const std::array<double, 3>& a, const std::array<double, 3>& b) {
    return (a[0] - b[0]) * (a[0] - b[0]) + (a[1] - b[1]) * (a[1] - b[1]) + (a[2] - b[2]) * (a[2] - b[2]);
  };
  std::vector<int> out;
  out.reserve(prototypes.size());
  for (const auto& p : prototypes) {
    int best = p.label;
    double bd = d2(p.lab, p.table_lab);
    for (const auto& q : prototypes)
      if (q.label != p.label && d2(p.lab, q.table_lab) < bd) bd = d2(p.lab, q.table_lab), best = q.label;
    out.push_back(best);
  }
  return out;
}

void validate(const SegmentOptions& o) {
  auto bad = [](const std::string& m) { throw Error("", m); };
  if (const std::string why = voxel_geometry_problem(o.spacing_m, o.origin_m); !why.empty()) bad(why);
  if (o.calibration_slices < 1 || o.calibration_slices > 64) bad("calibration-slices: must be in 1..64");
  if (o.bit_depth < 8 || o.bit_depth > 16) bad("bit-depth: must be in 8..16");
  if (o.sample_stride < 1 || o.sample_stride > 64) bad("sample stride must be in 1..64 (the library's SegmentOptions::sample_stride)");
  if (o.refine_iterations < 0 || o.refine_iterations > 100) bad("refine-iterations: must be in 0..100");
  if (!(o.refine_prior >= 0) || !std::isfinite(o.refine_prior)) bad("refine prior must be >= 0 (the library's SegmentOptions::refine_prior)");
  if (!(o.refine_max_shift >= 0) || !std::isfinite(o.refine_max_shift)) bad("refine-max-shift: must be >= 0");
  if (!(o.lightness_weight > 0) || !std::isfinite(o.lightness_weight)) bad("lightness-weight: must be > 0");
  // CIELAB's lightness axis: in RGB the weight would be ignored without a word
  if (o.colour_space != SegmentOptions::Space::cielab && o.lightness_weight != 1)
    bad("lightness-weight: weighs CIELAB's lightness; pass --colour-space cielab with it");
  if (!(o.smoothness >= 0) || !std::isfinite(o.smoothness)) bad("smoothness: must be >= 0 (0: off)");
  if (o.smoothing_sweeps < 1 || o.smoothing_sweeps > 16) bad("smoothing-sweeps: must be in 1..16");
  if (o.speck_support < 0 || o.speck_support > 26) bad("speck-support: must be in 0..26");
  if (o.min_island_voxels < 0) bad("min-island: must be >= 0");
  if (!(o.min_island_mm3 >= 0) || !std::isfinite(o.min_island_mm3)) bad("min-island-mm3: must be >= 0 mm^3");
  if (o.min_vessel_voxels < 0) bad("min-vessel: must be >= 0");
  if (!(o.min_body_fraction > 0 && o.min_body_fraction <= 1)) bad("min-body-fraction: must be in (0, 1]");
  if (o.slab < 1 || o.slab > 256) bad("slab: must be in 1..256");
  if (o.scratch_memory_bytes < 0) bad("scratch memory must be >= 0 (the library's SegmentOptions::scratch_memory_bytes)");
  const auto& r = o.roi_px;
  if (r[0] < 0 || r[1] < 0 || r[2] < 0 || r[3] < 0 || (r[2] == 0) != (r[3] == 0))
    bad("roi: x and y must be >= 0 and width and height both > 0 (or both 0: whole slices)");
  if (o.first_slice < 0) bad("slices: the first slice must be >= 0");
  if (o.last_slice < -1 || (o.last_slice >= 0 && o.last_slice < o.first_slice))
    bad("slices: the last slice must be >= the first (or -1: to the last)");
  validate(o.registration);
}

bool has_roi(const SegmentOptions& o) { return o.roi_px[2] > 0 || o.first_slice > 0 || o.last_slice >= 0; }

std::array<int, 3> roi_offset(const SegmentOptions& o) {
  return {o.roi_px[2] > 0 ? o.roi_px[0] : 0, o.roi_px[2] > 0 ? o.roi_px[1] : 0, o.first_slice};
}

std::array<double, 3> volume_origin(const SegmentOptions& o) {
  const std::array<int, 3> off = roi_offset(o);
  std::array<double, 3> v{};
  for (int k = 0; k < 3; ++k) v[k] = o.origin_m[k] + off[k] * o.spacing_m[k];
  return v;
}

SliceSource roi_source(SliceSource src, const SegmentOptions& o) {
  if (!has_roi(o)) return src;
  const std::array<int, 3> off = roi_offset(o);
  const int nx = o.roi_px[2] > 0 ? o.roi_px[2] : src.nx, ny = o.roi_px[3] > 0 ? o.roi_px[3] : src.ny;
  const int last = o.last_slice >= 0 ? o.last_slice : src.nz - 1;
  if (off[0] + static_cast<std::int64_t>(nx) > src.nx || off[1] + static_cast<std::int64_t>(ny) > src.ny)
    throw Error(src.name, "the region of interest (x " + std::to_string(off[0]) + ", y " + std::to_string(off[1]) +
                              ", " + std::to_string(nx) + " x " + std::to_string(ny) +
                              " px) reaches beyond the slices, which are " + std::to_string(src.nx) + " x " +
                              std::to_string(src.ny) + " px");
  if (last >= src.nz || off[2] > last)
    throw Error(src.name, "the slices " + std::to_string(off[2]) + ".." + std::to_string(last) +
                              " reach beyond the stack, which has " + std::to_string(src.nz) + " (0.." +
                              std::to_string(src.nz - 1) + ")");
  auto in = std::make_shared<SliceSource>(std::move(src));
  SliceSource s;
  s.nx = nx, s.ny = ny, s.nz = last - off[2] + 1;
  s.name = in->name, s.note = in->note;
  s.read = [in, off, nx, ny](int z, std::vector<std::uint8_t>& rgb) {
    if (in->read_region && (nx != in->nx || ny != in->ny)) {  // the file's decoder cuts (read_slice's region)
      in->read_region(z + off[2], {off[0], off[1], nx, ny}, rgb);
      return;
    }
    std::vector<std::uint8_t> raw;
    in->read(z + off[2], raw);
    if (raw.size() != static_cast<std::size_t>(in->nx) * in->ny * 3)  // (never cut past a short slice)
      throw Error(in->name, "slice " + std::to_string(z + off[2]) + " has the wrong size");
    if (nx == in->nx && ny == in->ny) {
      rgb = std::move(raw);
      return;
    }
    rgb.resize(static_cast<std::size_t>(nx) * ny * 3);
    const std::size_t row = static_cast<std::size_t>(nx) * 3;
    for (int y = 0; y < ny; ++y)
      std::memcpy(rgb.data() + y * row, raw.data() + ((static_cast<std::size_t>(y) + off[1]) * in->nx + off[0]) * 3, row);
  };
  return s;
}

std::string segment_parameters_json(const SegmentOptions& o) {
  nlohmann::json j;
  j["spacing_m"] = o.spacing_m;
  j["origin_m"] = o.origin_m;
  j["roi_px"] = o.roi_px;
  j["first_slice"] = o.first_slice;
  j["last_slice"] = o.last_slice;
  j["calibration_slices"] = o.calibration_slices;
  j["sample_stride"] = o.sample_stride;
  j["normalise"] = to_string(o.normalise);
  j["classify"] = to_string(o.classify);
  j["colour_space"] = to_string(o.colour_space);
  j["refine_iterations"] = o.refine_iterations;
  j["refine_prior"] = o.refine_prior;
  j["refine_max_shift"] = o.refine_max_shift;
  j["exposure_from_border"] = o.exposure_from_border;
  j["register_slices"] = o.register_slices;
  if (o.register_slices)
    j["registration"] = {{"half_window", o.registration.half_window},
                         {"max_shift_px", o.registration.max_shift_px},
                         {"min_response", o.registration.min_response}};
  j["lightness_weight"] = o.lightness_weight;
  j["smoothness"] = o.smoothness;
  j["smoothing_sweeps"] = o.smoothing_sweeps;
  j["cleanup"] = o.cleanup;
  j["enforce_order"] = o.enforce_order;
  j["fill_holes"] = o.fill_holes;
  j["speck_support"] = o.speck_support;
  j["min_island_voxels"] = o.min_island_voxels;
  j["min_island_mm3"] = o.min_island_mm3;
  j["min_vessel_voxels"] = o.min_vessel_voxels;
  j["min_body_fraction"] = o.min_body_fraction;
  j["slab"] = o.slab;
  return j.dump();
}

std::vector<std::string> label_inside(const TissueTable& table) {
  std::vector<std::string> names = table.label_names();
  std::vector<std::string> inside(names.size());
  for (const auto& t : table.tissues) inside[t.label] = t.inside;
  return inside;
}

namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// OpenCV's own threads off while we parallelise over slices.
struct CvThreads {
  int saved;
  CvThreads() : saved(cv::getNumThreads()) { cv::setNumThreads(1); }
  ~CvThreads() { cv::setNumThreads(saved); }
};

// The run-length scratch between the passes: in memory up to a limit, then
// in an unlinked file.
class Scratch {
 public:
  Scratch(std::int64_t limit, std::string dir) : limit_(limit), dir_(std::move(dir)) {}
  ~Scratch() {
    if (fd_ >= 0) ::close(fd_);
  }
  void append(const std::vector<std::uint8_t>& blob) {
    index_.push_back({total_, blob.size()});
    if (fd_ < 0 && static_cast<std::int64_t>(mem_.size() + blob.size()) > limit_) spill();
    if (fd_ >= 0) {
      write_all(blob.data(), blob.size(), total_);
    } else {
      mem_.insert(mem_.end(), blob.begin(), blob.end());
    }
    total_ += blob.size();
  }
  void read(int z, std::vector<std::uint8_t>& out) const {
    const auto [at, size] = index_[static_cast<std::size_t>(z)];
    out.resize(size);
    if (fd_ < 0) {
      std::memcpy(out.data(), mem_.data() + at, size);
      return;
    }
    std::size_t done = 0;
    while (done < size) {
      const ssize_t r = ::pread(fd_, out.data() + done, size - done, static_cast<off_t>(at + done));
      if (r <= 0) throw Error(path_, "cannot read the segmentation scratch file");
      done += static_cast<std::size_t>(r);
    }
  }
  std::uint64_t bytes() const { return total_; }
  bool spilled() const { return fd_ >= 0; }

 private:
  void spill() {
    const std::string dir = dir_.empty() ? std::filesystem::temp_directory_path().string() : dir_;
    std::string tmpl = dir + "/orthosim-segment-XXXXXX";
    std::vector<char> buf(tmpl.begin(), tmpl.end());
    buf.push_back('\0');
    fd_ = ::mkstemp(buf.data());
    if (fd_ < 0) throw Error(dir, "cannot create a scratch file for segmentation");
    path_ = buf.data();
    ::unlink(buf.data());  // gone when closed, whatever happens
    write_all(mem_.data(), mem_.size(), 0);
    mem_.clear();
    mem_.shrink_to_fit();
  }
  void write_all(const std::uint8_t* p, std::size_t n, std::uint64_t at) {
    std::size_t done = 0;
    while (done < n) {
      const ssize_t w = ::pwrite(fd_, p + done, n - done, static_cast<off_t>(at + done));
      if (w <= 0) throw Error(path_, "cannot write the segmentation scratch file (disk full?)");
      done += static_cast<std::size_t>(w);
    }
  }
  std::int64_t limit_;
  std::string dir_, path_;
  int fd_ = -1;
  std::vector<std::uint8_t> mem_;
  std::vector<std::pair<std::uint64_t, std::size_t>> index_;
  std::uint64_t total_ = 0;
};

std::vector<int> calibration_indices(int nz, int k) {
  k = std::min(k, nz);
  std::vector<int> z;
  for (int i = 0; i < k; ++i) {
    const int v = k == 1 ? nz / 2 : static_cast<int>(std::lround(static_cast<double>(i) * (nz - 1) / (k - 1)));
    if (z.empty() || z.back() != v) z.push_back(v);
  }
  return z;
}

void check_table(const TissueTable& table) {
  if (table.tissues.empty()) throw Error(table.path, "the tissue table has no tissues");
  for (const auto& t : table.tissues)
    if (t.rgb.empty()) throw Error(table.path, "tissue '" + t.name + "' has no colour prototype");
}

}  // namespace

// ---- the driver --------------------------------------------------------------------

SegmentMetrics segment(const SliceSource& whole, const TissueTable& table, const SegmentOptions& opt,
                       const LabelSink& sink, const std::function<void(long, long)>& progress) {
  validate(opt);
  check_table(table);
  if (whole.nx <= 0 || whole.ny <= 0 || whole.nz <= 0) throw Error(whole.name, "empty stack");
  const SliceSource stack = roi_source(whole, opt);
  CvThreads cv_threads;
  SegmentMetrics met;
  met.stack_size = {whole.nx, whole.ny, whole.nz};
  // registered: every later read (calibration, both passes) sees moved slices
  if (opt.register_slices) met.registration = register_slices(stack, opt.registration);
  const SliceSource src = opt.register_slices ? shifted_source(stack, met.registration.shift) : stack;
  const int nx = src.nx, ny = src.ny, nz = src.nz;
  const std::size_t plane = static_cast<std::size_t>(nx) * ny;
  met.nx = nx, met.ny = ny, met.nz = nz;
  met.stack_note = src.note;
  auto report = [&](long done) {
    if (progress) progress(done, 2L * nz);
  };

  const LabelInfo info = make_label_info(table, opt.fill_holes);
  ColourModel model = initial_model(table, opt);
  model.reset_table();

  // ---- calibration
  auto t0 = std::chrono::steady_clock::now();
  {
    const std::vector<int> zs = calibration_indices(nz, opt.calibration_slices);
    std::vector<std::vector<std::uint8_t>> slices(zs.size());
    tbb::parallel_for(std::size_t(0), zs.size(), [&](std::size_t k) { src.read(zs[k], slices[k]); });
    calibrate(model, slices, nx, ny, opt);
  }
  met.calibrate_s = seconds_since(t0);
  met.exposure = model.exposure;
  for (const auto& c : model.centres) {
    Prototype p;
    p.label = c.label;
    p.table_lab = c.table_lab;
    p.lab = c.lab;
    p.pixel_lab = c.pixel_lab;
    p.samples = c.samples;
    met.prototypes.push_back(p);
  }
  if (model.mahalanobis) {
    std::map<std::pair<int, int>, double> closest;
    for (std::size_t i = 0; i < model.centres.size(); ++i)
      for (std::size_t k = i + 1; k < model.centres.size(); ++k) {
        const Centre &p = model.centres[i], &q = model.centres[k];
        if (p.label == q.label) continue;
        const auto key = std::minmax(p.label, q.label);
        const double d = std::sqrt(mahalanobis2(model.precision, p.pixel_x, q.pixel_x));
        auto [it, fresh] = closest.try_emplace(key, d);
        if (!fresh) it->second = std::min(it->second, d);
      }
    for (const auto& [ab, d] : closest) met.separations.push_back({ab.first, ab.second, d});
    std::stable_sort(met.separations.begin(), met.separations.end(),
                     [](const auto& x, const auto& y) { return x.delta < y.delta; });
  }

  // ---- pass 1: classify, smooth, order, rank filter, runs, 3-D components
  Scratch scratch(opt.scratch_memory_bytes, opt.scratch_dir);
  ComponentTracker tracker;
  std::map<int, std::vector<std::uint8_t>> l1;  // classified slices waiting for the rank filter
  SliceRuns prev_runs;
  bool have_prev = false;
  int next_filter = 0;
  std::atomic<std::int64_t> order_changed{0}, speck_changed{0}, smooth_changed{0};
  std::vector<double> gains(static_cast<std::size_t>(nz), 1.0);
  std::vector<std::uint8_t> fallbacks(static_cast<std::size_t>(nz), 0);
  std::vector<double> read_cpu(static_cast<std::size_t>(nz), 0.0);
  tbb::enumerable_thread_specific<SliceWork> works;
  std::vector<std::uint8_t> blob;
  const bool cleanup = opt.cleanup;
  // The smoothness prior (SegmentOptions::smoothness) needs each slice's
  // colours and first labels until its last sweep is done, and that needs
  // the slices `sweeps` ahead: slab [a, b) is classified ahead to b + sweeps,
  // and the result is what sweeps over the whole stack at once would give.
  const bool smooth = opt.smoothness > 0 && model.mahalanobis;
  const int sweeps = smooth ? opt.smoothing_sweeps : 0;
  const Smoother smoother = smooth ? make_smoother(model, opt.smoothness, opt.spacing_m) : Smoother{};
  struct Classified {
    std::vector<std::uint8_t> colour, labels;
  };
  std::map<int, Classified> l0;  // with the prior: classified slices within reach of a sweep
  int next_classify = 0;
  // The sweeps as a wavefront along the stack: lev[t] holds the labels after
  // sweep t (lev[0]: the first), each slice's uniform_3x3 and what sweep t
  // changed; sweep t of a slice is computed once, as soon as sweep t - 1 of its
  // neighbours is, and done[t] is the first slice it has not reached.
  struct Level {
    std::vector<std::uint8_t> labels, uniform, active, rows;
  };
  std::vector<std::map<int, Level>> lev(static_cast<std::size_t>(sweeps) + 1);
  std::vector<int> done(static_cast<std::size_t>(sweeps) + 1, 0);
  // levels no longer needed, their buffers kept for the next slices (a fresh
  // megabyte a slice cost page faults)
  std::vector<Level> spare;
  auto take = [&](std::map<int, Level>& m, int z) -> Level& {
    Level& L = m[z];
    if (!spare.empty()) L = std::move(spare.back()), spare.pop_back();
    L.labels.resize(plane);
    return L;
  };
  auto release = [&](std::map<int, Level>& m, int below) {
    while (!m.empty() && m.begin()->first < below) {
      spare.push_back(std::move(m.begin()->second));
      m.erase(m.begin());
    }
  };
  for (int a = 0; a < nz; a += opt.slab) {
    const int b = std::min(nz, a + opt.slab);
    t0 = std::chrono::steady_clock::now();
    const int c0 = next_classify, c1 = std::min(nz, b + sweeps);
    std::vector<Classified> fresh(static_cast<std::size_t>(c1 - c0));
    tbb::parallel_for(c0, c1, [&](int z) {
      SliceWork& w = works.local();
      std::vector<std::uint8_t>& rgb = w.rgb;
      const auto tr = std::chrono::steady_clock::now();
      src.read(z, rgb);
      if (rgb.size() != 3 * plane) throw Error(src.name, "slice " + std::to_string(z) + " has the wrong size");
      read_cpu[static_cast<std::size_t>(z)] = seconds_since(tr);
      Classified& f = fresh[static_cast<std::size_t>(z - c0)];
      f.labels.resize(plane);
      const GainField g = classify_slice(model, opt, rgb.data(), nx, ny, w, f.labels.data());
      gains[static_cast<std::size_t>(z)] = g.mean_gain();
      fallbacks[static_cast<std::size_t>(z)] = g.fallback;
      if (smooth)
        f.colour.assign(w.colour, w.colour + 3 * plane);
      else if (cleanup && opt.enforce_order)
        order_changed += enforce_order(info, model, w.colour, nx, ny, f.labels.data());
    });
    next_classify = c1;
    if (!smooth) {
      for (int z = c0; z < c1; ++z) l1[z] = std::move(fresh[static_cast<std::size_t>(z - c0)].labels);
    } else {
      for (int z = c0; z < c1; ++z) l0[z] = std::move(fresh[static_cast<std::size_t>(z - c0)]);
      // lev[0]: the first labels of the new slices
      for (int z = c0; z < c1; ++z) {
        Level& L = take(lev[0], z);
        std::copy(l0.at(z).labels.begin(), l0.at(z).labels.end(), L.labels.begin());
      }
      tbb::parallel_for(c0, c1, [&](int z) {
        Level& L = lev[0].at(z);
        uniform_3x3(L.labels.data(), nx, ny, L.uniform);
      });
      done[0] = c1;
      for (int t = 1; t <= sweeps; ++t) {
        // sweep t of slice z needs sweep t - 1 of z - 1, z and z + 1 (the
        // stack's first and last slices see their one neighbour on both
        // sides, a mirror, so that slices that do not change along the stack
        // keep labels that do not either)
        const int from = done[t], to = done[t - 1] == nz ? nz : done[t - 1] - 1;
        if (to <= from) continue;
        for (int z = from; z < to; ++z) take(lev[static_cast<std::size_t>(t)], z);
        auto& prevl = lev[static_cast<std::size_t>(t - 1)];
        auto slice = [&](int z) {
          if (z < 0) z = nz > 1 ? 1 : -1;
          if (z >= nz) z = nz > 1 ? nz - 2 : -1;
          if (z < 0) return SweepSlice{};
          const Level& L = prevl.at(z);
          return SweepSlice{L.labels.data(), L.uniform.data(), t > 1 ? L.active.data() : nullptr,
                            t > 1 ? L.rows.data() : nullptr};
        };
        tbb::parallel_for(from, to, [&](int z) {
          Level& L = lev[static_cast<std::size_t>(t)].at(z);
          smooth_sweep(smoother, model, l0.at(z).colour.data(), slice(z - 1), slice(z), slice(z + 1), nx, ny,
                       L.labels.data());
          // what this sweep changed (the next sweep looks only there), and the
          // uniform_3x3 of the result (the last one's if nothing changed)
          const Level& P = prevl.at(z);
          if (changed_3x3(L.labels.data(), P.labels.data(), nx, ny, L.active, L.rows))
            uniform_3x3(L.labels.data(), nx, ny, L.uniform);
          else
            L.uniform = P.uniform;
        });
        done[static_cast<std::size_t>(t)] = to;
      }
      auto& last = lev[static_cast<std::size_t>(sweeps)];
      tbb::parallel_for(a, b, [&](int z) {
        std::vector<std::uint8_t>& lab = last.at(z).labels;
        const std::vector<std::uint8_t>& first = l0.at(z).labels;
        std::int64_t n = 0;
        for (std::size_t i = 0; i < plane; ++i) n += lab[i] != first[i];
        smooth_changed += n;
        if (cleanup && opt.enforce_order) order_changed += enforce_order(info, model, l0.at(z).colour.data(), nx, ny, lab.data());
      });
      for (int z = a; z < b; ++z) l1[z] = last.at(z).labels;
      // what no later sweep needs: level t's slices below the next sweep's first but one
      for (int t = 0; t < sweeps; ++t) release(lev[static_cast<std::size_t>(t)], done[static_cast<std::size_t>(t) + 1] - 1);
      release(last, b);
      while (!l0.empty() && l0.begin()->first < b) l0.erase(l0.begin());
    }
    met.classify_s += seconds_since(t0);

    t0 = std::chrono::steady_clock::now();
    const int q = b == nz ? nz : b - 1;  // slice z needs z+1 classified
    const int p = next_filter;
    std::vector<std::vector<std::uint8_t>> l2(static_cast<std::size_t>(q - p));
    std::vector<SliceRuns> runs(static_cast<std::size_t>(q - p));
    tbb::parallel_for(p, q, [&](int z) {
      auto& out = l2[static_cast<std::size_t>(z - p)];
      out.resize(plane);
      const std::uint8_t* prev = z > 0 ? l1.at(z - 1).data() : nullptr;
      const std::uint8_t* next = z + 1 < nz ? l1.at(z + 1).data() : nullptr;
      speck_changed += rank_filter(info, cleanup ? opt.speck_support : 0, prev, l1.at(z).data(), next, nx, ny,
                                   out.data());
      make_runs(out.data(), nx, ny, runs[static_cast<std::size_t>(z - p)]);
    });
    for (int z = p; z < q; ++z) {
      SliceRuns& r = runs[static_cast<std::size_t>(z - p)];
      tracker.add_slice(r, have_prev ? &prev_runs : nullptr);
      encode_runs(r, blob);
      scratch.append(blob);
      prev_runs = std::move(r);
      have_prev = true;
    }
    next_filter = q;
    while (!l1.empty() && l1.begin()->first < q - 1) l1.erase(l1.begin());
    met.cleanup_s += seconds_since(t0);
    report(q);
  }
  for (double r : read_cpu) met.read_s += r;
  met.order_changed = order_changed;
  met.speck_changed = speck_changed;
  met.smooth_changed = smooth_changed;
  met.gain_min = *std::min_element(gains.begin(), gains.end());
  met.gain_max = *std::max_element(gains.begin(), gains.end());
  for (auto f : fallbacks) met.normalise_fallbacks += f;
  met.scratch_bytes = static_cast<std::int64_t>(scratch.bytes());
  met.scratch_spilled = scratch.spilled();

  // ---- components
  t0 = std::chrono::steady_clock::now();
  ComponentTracker::Decision dec;
  const std::vector<std::uint8_t> final_label = tracker.resolve(info, opt, &dec);
  met.components = dec.components;
  met.holes_filled = dec.holes_filled;
  met.islands_absorbed = dec.islands_absorbed;
  met.misplaced_absorbed = dec.misplaced_absorbed;
  met.detached_removed = dec.detached_removed;
  met.body_components = dec.body_components;
  met.components_s = seconds_since(t0);
  if (dec.body_components == 0)
    throw Error(src.name, "nothing segmented: every voxel was classified as background (are the tissue table's "
                          "colours those of this stack?" + (src.note.empty() ? std::string() : " " + src.note) + ")");

  // ---- pass 2: final labels, in z order, to the sink
  t0 = std::chrono::steady_clock::now();
  std::vector<std::int64_t> count(256, 0);
  std::mutex count_mutex;
  const int slab2 = std::max(opt.slab, 1);
  std::vector<std::uint8_t> out(static_cast<std::size_t>(slab2) * plane);
  for (int a = 0; a < nz; a += slab2) {
    const int b = std::min(nz, a + slab2);
    tbb::parallel_for(a, b, [&](int z) {
      std::vector<std::uint8_t> bl;
      scratch.read(z, bl);
      std::uint8_t* dst = out.data() + static_cast<std::size_t>(z - a) * plane;
      decode_runs(bl.data(), bl.size(), nx, ny, final_label.data() + tracker.slice_offset(z), dst);
      std::array<std::int64_t, 256> c{};
      for (std::size_t i = 0; i < plane; ++i) ++c[dst[i]];
      std::lock_guard<std::mutex> lock(count_mutex);
      for (int l = 0; l < 256; ++l) count[static_cast<std::size_t>(l)] += c[static_cast<std::size_t>(l)];
    });
    sink(a, b - a, out.data());
    report(nz + b);
  }
  met.write_s = seconds_since(t0);
  const std::vector<std::string> names = table.label_names();
  for (std::size_t l = 0; l < names.size(); ++l)
    if (!names[l].empty()) met.voxels[names[l]] = count[l];
  return met;
}

Volume segment_volume(const SliceSource& src, const TissueTable& table, const SegmentOptions& opt,
                      SegmentMetrics* metrics) {
  const SliceSource roi = roi_source(src, opt);
  Volume v;
  v.nx = roi.nx, v.ny = roi.ny, v.nz = roi.nz;
  v.spacing_m = opt.spacing_m;
  v.origin_m = volume_origin(opt);
  v.label_names = table.label_names();
  v.labels.resize(static_cast<std::size_t>(v.nx) * v.ny * v.nz);
  const std::size_t plane = static_cast<std::size_t>(v.nx) * v.ny;
  SegmentMetrics m = segment(src, table, opt, [&](int z0, int n, const std::uint8_t* labels) {
    std::memcpy(v.labels.data() + static_cast<std::size_t>(z0) * plane, labels, static_cast<std::size_t>(n) * plane);
  });
  if (metrics) *metrics = m;
  return v;
}

// ---- files ---------------------------------------------------------------------------

namespace {

std::string nrrd_header(int nx, int ny, int nz, const std::array<double, 3>& spacing_m,
                        const std::array<double, 3>& origin_m, const std::vector<std::string>& names) {
  std::ostringstream h;
  h.precision(17);
  h << "NRRD0004\n";
  h << "# orthosim segment: tissue labels; image frame (x columns, y rows, z slices) as LPS, mm\n";
  for (std::size_t l = 0; l < names.size(); ++l)
    if (!names[l].empty()) h << "# label " << l << " = " << names[l] << "\n";
  h << "type: uint8\n";
  h << "dimension: 3\n";
  h << "space: left-posterior-superior\n";
  h << "sizes: " << nx << " " << ny << " " << nz << "\n";
  const double s[3] = {spacing_m[0] * 1e3, spacing_m[1] * 1e3, spacing_m[2] * 1e3};
  h << "space directions: (" << s[0] << ",0,0) (0," << s[1] << ",0) (0,0," << s[2] << ")\n";
  h << "kinds: domain domain domain\n";
  h << "endian: little\n";
  h << "encoding: raw\n";
  h << "space origin: (" << origin_m[0] * 1e3 << "," << origin_m[1] * 1e3 << "," << origin_m[2] * 1e3
    << ")\n";
  for (std::size_t l = 0; l < names.size(); ++l)
    if (!names[l].empty()) h << "orthosim_label_" << l << ":=" << names[l] << "\n";
  h << "\n";
  return h.str();
}

}  // namespace

SegmentMetrics segment_stack(const SegmentFiles& files, const TissueTable& table, const SegmentOptions& opt,
                             const std::function<void(long, long)>& progress) {
  const auto t_start = std::chrono::steady_clock::now();
  validate(opt);
  check_table(table);
  check_output_file(files.out_h5);
  if (!files.nrrd_path.empty()) check_output_file(files.nrrd_path);
  const SliceSource whole = stack_source(files.stack_dir, opt.bit_depth);
  const SliceSource src = roi_source(whole, opt);  // the labels' size (segment cuts `whole` itself)

  ModelWriter w(files.out_h5, ModelWriter::Start::fresh);
  const std::string g = "/volume";
  w.h5().make_groups(g);
  w.h5().create<std::uint8_t>(g + "/labels",
                              {static_cast<std::uint64_t>(src.nz), static_cast<std::uint64_t>(src.ny),
                               static_cast<std::uint64_t>(src.nx)},
                              "label", "tissue labels [nz][ny][nx]; values index label_names");
  std::optional<AtomicFile> nrrd;
  std::ofstream nrrd_out;
  const std::vector<std::string> names = table.label_names();
  if (!files.nrrd_path.empty()) {
    nrrd.emplace(files.nrrd_path);
    nrrd_out.open(nrrd->temp(), std::ios::binary);
    if (!nrrd_out) throw Error(files.nrrd_path, "cannot write NRRD file");
    nrrd_out << nrrd_header(src.nx, src.ny, src.nz, opt.spacing_m, volume_origin(opt), names);
  }
  const std::size_t plane = static_cast<std::size_t>(src.nx) * src.ny;
  SegmentMetrics m = segment(whole, table, opt, [&](int z0, int n, const std::uint8_t* labels) {
    w.h5().write_rows<std::uint8_t>(g + "/labels", static_cast<std::uint64_t>(z0), static_cast<std::uint64_t>(n),
                                    labels);
    if (nrrd) {
      nrrd_out.write(reinterpret_cast<const char*>(labels), static_cast<std::streamsize>(n * plane));
      if (!nrrd_out) throw Error(files.nrrd_path, "cannot write NRRD file (disk full?)");
    }
  }, progress);
  w.h5().set_attr(g, "spacing_m", std::vector<double>(opt.spacing_m.begin(), opt.spacing_m.end()));
  const std::array<double, 3> origin = volume_origin(opt);
  w.h5().set_attr(g, "origin_m", std::vector<double>(origin.begin(), origin.end()));
  // where the labels lie in the slice files (remesh's texture reads the files)
  const std::array<int, 3> off = roi_offset(opt);
  w.h5().set_attr(g, "stack_offset_voxels", std::vector<double>(off.begin(), off.end()));
  // and what the slice files were: remesh's texture refuses another stack
  w.h5().set_attr(g, "stack_shape_voxels", std::vector<double>{static_cast<double>(whole.nx),
                                                               static_cast<double>(whole.ny),
                                                               static_cast<double>(whole.nz)});
  w.h5().set_attr(g, "label_names", names);
  w.h5().set_attr(g, "label_inside", label_inside(table));
  if (opt.register_slices) {
    // what anything reading colours from the stack must apply too (remesh's texture)
    std::vector<std::int32_t> sh;
    for (const auto& s : m.registration.shift) sh.push_back(s[0]), sh.push_back(s[1]);
    w.h5().write<std::int32_t>(g + "/slice_shift_px", sh.data(), {static_cast<std::uint64_t>(src.nz), 2}, "px",
                               "(x, y) each slice was moved by before segmentation (segment --register)");
  }

  std::string inputs = files.inputs_json;
  if (inputs.empty()) {
    nlohmann::json j;
    j[files.stack_dir] = hash_stack(files.stack_dir, opt.first_slice, opt.last_slice);
    if (!files.tissues_path.empty()) j[files.tissues_path] = hash_path(files.tissues_path);
    inputs = j.dump();
  }
  w.write("segment", make_provenance(files.command_line, inputs, segment_parameters_json(opt), 0,
                                     seconds_since(t_start)));
  if (nrrd) {
    nrrd_out.close();
    if (!nrrd_out) throw Error(files.nrrd_path, "cannot write NRRD file");
  }
  w.commit();
  if (nrrd) nrrd->commit();
  return m;
}

// ---- evaluation ------------------------------------------------------------------------

namespace {

struct DiceAcc {
  // by tissue name: |A|, |B|, |A n B|
  std::map<std::string, std::array<std::int64_t, 3>> acc;
  std::vector<int> a_to_b;  // label of A -> label of B with the same name, or -1
  std::vector<std::string> a_names, b_names;
  void init(const std::vector<std::string>& a, const std::vector<std::string>& b) {
    a_names = a, b_names = b;
    a_to_b.assign(256, -1);
    for (std::size_t i = 1; i < a.size(); ++i)
      for (std::size_t j = 1; j < b.size(); ++j)
        if (!a[i].empty() && a[i] == b[j]) a_to_b[i] = static_cast<int>(j);
  }
  void add(const std::uint8_t* a, const std::uint8_t* b, std::size_t n) {
    std::array<std::int64_t, 256> ca{}, cb{}, both{};
    for (std::size_t i = 0; i < n; ++i) {
      ++ca[a[i]], ++cb[b[i]];
      if (a_to_b[a[i]] >= 0 && a_to_b[a[i]] == b[i]) ++both[a[i]];
    }
    for (std::size_t l = 1; l < a_names.size(); ++l)
      if (a_to_b[l] >= 0) {
        auto& e = acc[a_names[l]];
        e[0] += ca[l], e[1] += cb[static_cast<std::size_t>(a_to_b[l])], e[2] += both[l];
      }
  }
  std::map<std::string, double> result(std::map<std::string, std::int64_t>* truth_voxels) const {
    std::map<std::string, double> d;
    for (const auto& [name, e] : acc) {
      if (truth_voxels) (*truth_voxels)[name] = e[1];
      if (e[0] + e[1] == 0) continue;
      d[name] = 2.0 * static_cast<double>(e[2]) / static_cast<double>(e[0] + e[1]);
    }
    return d;
  }
};

}  // namespace

std::map<std::string, double> dice_per_tissue(const Volume& labels, const Volume& truth,
                                              std::map<std::string, std::int64_t>* truth_voxels) {
  if (labels.nx != truth.nx || labels.ny != truth.ny || labels.nz != truth.nz)
    throw Error("", "dice: the volumes differ in size");
  DiceAcc acc;
  acc.init(labels.label_names, truth.label_names);
  acc.add(labels.labels.data(), truth.labels.data(), labels.labels.size());
  return acc.result(truth_voxels);
}

std::map<std::string, double> dice_per_tissue(const std::string& labels_h5, const std::string& truth_h5,
                                              std::map<std::string, std::int64_t>* truth_voxels,
                                              const std::array<int, 3>& truth_offset) {
  ModelReader a(labels_h5), b(truth_h5);
  const std::string ds = "/volume/labels";
  if (!a.has(ds)) throw Error(labels_h5, "missing dataset /volume/labels");
  if (!b.has(ds)) throw Error(truth_h5, "missing dataset /volume/labels");
  const auto da = a.h5().dims(ds), db = b.h5().dims(ds);
  if (da.size() != 3 || db.size() != 3) throw Error(truth_h5, "truth volume size differs from " + labels_h5);
  // the labels' voxel (i, j, k) is the truth's (i, j, k) + truth_offset
  const std::uint64_t ox = static_cast<std::uint64_t>(truth_offset[0]), oy = static_cast<std::uint64_t>(truth_offset[1]),
                      oz = static_cast<std::uint64_t>(truth_offset[2]);
  if (truth_offset[0] < 0 || truth_offset[1] < 0 || truth_offset[2] < 0 || ox + da[2] > db[2] || oy + da[1] > db[1] ||
      oz + da[0] > db[0])
    throw Error(truth_h5, "truth volume size differs from " + labels_h5);
  DiceAcc acc;
  acc.init(a.h5().attr_strings("/volume", "label_names"), b.h5().attr_strings("/volume", "label_names"));
  const std::uint64_t plane = da[1] * da[2], tplane = db[1] * db[2];
  const std::uint64_t slab = std::max<std::uint64_t>(1, (64u << 20) / std::max<std::uint64_t>(tplane, 1));
  std::vector<std::uint8_t> x, y, t;
  for (std::uint64_t z = 0; z < da[0]; z += slab) {
    const std::uint64_t n = std::min(slab, da[0] - z);
    x.resize(n * plane), y.resize(n * plane);
    a.h5().read_rows<std::uint8_t>(ds, z, n, x.data());
    if (db == da) {
      b.h5().read_rows<std::uint8_t>(ds, z, n, y.data());
    } else {
      t.resize(n * tplane);
      b.h5().read_rows<std::uint8_t>(ds, z + oz, n, t.data());
      for (std::uint64_t k = 0; k < n; ++k)
        for (std::uint64_t j = 0; j < da[1]; ++j)
          std::memcpy(y.data() + k * plane + j * da[2], t.data() + k * tplane + (j + oy) * db[2] + ox, da[2]);
    }
    acc.add(x.data(), y.data(), x.size());
  }
  return acc.result(truth_voxels);
}

}  // namespace orthosim
