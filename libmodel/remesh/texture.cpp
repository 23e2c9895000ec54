// Texture baking from the colour stack (OpenCV for image I/O only).
#include "libmodel/remesh/texture.h"

#include "libmodel/format/atomic.h"
#include "libmodel/remesh/detail.h"
#include "libmodel/segment/segment.h"

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <list>
#include <map>

namespace orthosim {

namespace fs = std::filesystem;
using Vec3 = Eigen::Vector3d;

ColourStack open_colour_stack(const std::string& dir, const std::array<double, 3>& spacing_m,
                              const std::array<double, 3>& origin_m) {
  for (double s : spacing_m)
    if (!(s > 0) || !std::isfinite(s)) throw Error(dir, "voxel spacing must be positive");
  ColourStack st;
  st.spacing_m = spacing_m;
  st.origin_m = origin_m;
  fs::path root(dir);
  std::error_code ec;
  if (!fs::is_directory(root, ec)) throw Error(dir, "not a directory of colour slices");
  if (fs::is_directory(root / "slices", ec)) root /= "slices";
  // the order and the files segment read (a plain sort put s10 before s2:
  // the texture's slices scrambled against the labels')
  st.files = list_stack(root.string());
  SliceFormat f;
  read_slice(st.files[0], &f, 16);
  st.nx = f.nx, st.ny = f.ny;
  return st;
}

namespace {

// least-recently-used cache of RGB slices (of the stack's region when it has
// one), read as segment reads them (read_slice)
class SliceCache {
 public:
  SliceCache(const ColourStack& s, const std::array<int, 4>& region, int capacity)
      : s_(s), region_(region), cap_(std::max(2, capacity)) {}
  const cv::Mat& get(int k) {
    auto it = map_.find(k);
    if (it != map_.end()) {
      lru_.splice(lru_.begin(), lru_, it->second.second);
      return it->second.first;
    }
    SliceFormat f;
    RgbImage img = read_slice(s_.files[k], &f, s_.bit_depth, region_);
    if (f.nx != s_.nx || f.ny != s_.ny) throw Error(s_.files[k], "slice size differs from the first slice's");
    cv::Mat m = cv::Mat(img.ny, img.nx, CV_8UC3, img.rgb.data()).clone();
    if (!s_.shift.empty()) {
      const auto [dx, dy] = s_.shift[static_cast<std::size_t>(k)];
      if (dx != 0 || dy != 0) {  // as segment moved it: content to (x + dx, y + dy), edges replicated
        const cv::Mat t = (cv::Mat_<double>(2, 3) << 1, 0, dx, 0, 1, dy);
        cv::Mat moved;
        cv::warpAffine(m, moved, t, m.size(), cv::INTER_NEAREST, cv::BORDER_REPLICATE);
        m = std::move(moved);
      }
    }
    if (static_cast<int>(map_.size()) >= cap_) {
      map_.erase(lru_.back());
      lru_.pop_back();
    }
    lru_.push_front(k);
    return map_.emplace(k, std::make_pair(std::move(m), lru_.begin())).first->second.first;
  }

 private:
  const ColourStack& s_;
  std::array<int, 4> region_;
  int cap_;
  std::list<int> lru_;
  std::map<int, std::pair<cv::Mat, std::list<int>::iterator>> map_;
};

}  // namespace

TextureImage bake_texture(const Surface& outer, const TubeSweep& sweep, RingSampling around, int arc_window, const ColourStack& stack,
                          const TextureOptions& o, const std::string& name) {
  if (o.max_size < 16 || o.max_size > 16384) throw Error("", "texture max_size must be in 16..16384");
  const remesh_detail::Topology topo = remesh_detail::build_topology(outer, name, true);
  const remesh_detail::Slicer sl(outer, topo, sweep.centre.row(0).transpose(), sweep.axis_direction);
  const double texel = o.texel_m > 0 ? o.texel_m : std::min(stack.spacing_m[0], stack.spacing_m[1]);
  const double depth = o.depth_m >= 0 ? o.depth_m : std::min(stack.spacing_m[0], stack.spacing_m[1]);
  // perimeter of the middle ring sets the width
  const SweepPlane mid = sweep_plane(sweep, 0.5 * sweep.length_m);
  const auto mloops = sl.slice(mid);
  const auto& ml = remesh_detail::tube_loop(mloops, name, 0.5 * sweep.length_m, sweep.length_m);
  double perim = 0;
  for (std::size_t i = 0; i < ml.q.size(); ++i) perim += (ml.q[(i + 1) % ml.q.size()] - ml.q[i]).norm();
  TextureImage t;
  t.width = std::clamp(static_cast<int>(std::lround(perim / texel)), 16, o.max_size);
  t.height = std::clamp(static_cast<int>(std::lround(sweep.length_m / texel)), 16, o.max_size);
  t.rgb.assign(static_cast<std::size_t>(t.width) * t.height * 3, 0);
  std::vector<double> u(t.width);
  for (int a = 0; a < t.width; ++a) u[a] = (a + 0.5) / t.width;
  // the part of the slices read: the stack's region (none with shifts, whose
  // moved slices reach beyond it), else the whole slice
  const bool part = stack.shift.empty() && (stack.region[2] > 0 && stack.region[3] > 0);
  const std::array<int, 4> region = part ? stack.region : std::array<int, 4>{0, 0, stack.nx, stack.ny};
  if (region[0] < 0 || region[1] < 0 || region[2] < 1 || region[3] < 1 || region[0] + region[2] > stack.nx ||
      region[1] + region[3] > stack.ny)
    throw Error("", "texture: the stack's region lies outside its slices");
  SliceCache cache(stack, part ? region : std::array<int, 4>{0, 0, 0, 0}, o.cache_slices);
  std::vector<Vec3> pts, inward;
  const int nz = static_cast<int>(stack.files.size());
  for (int b = 0; b < t.height; ++b) {
    const double s = (b + 0.5) / t.height * sweep.length_m;
    const SweepPlane pl = sweep_plane(sweep, s);
    const auto loops = sl.slice(pl);
    remesh_detail::sample_loop(remesh_detail::tube_loop(loops, name, s, sweep.length_m), pl, around, arc_window, u, pts, &inward,
                               name);
    t.side_loops += static_cast<std::int64_t>(loops.size()) - 1;
    for (int a = 0; a < t.width; ++a) {
      const Vec3 p = pts[a] + depth * inward[a];
      double f[3];
      bool out = false;
      // in the region's pixels (the whole slice's without one)
      const int n[3] = {region[2], region[3], nz};
      const int first[3] = {region[0], region[1], 0};
      int i0[3];
      double w[3];
      for (int d = 0; d < 3; ++d) {
        f[d] = (p(d) - stack.origin_m[d]) / stack.spacing_m[d] - first[d];
        if (f[d] < -0.5 || f[d] > n[d] - 0.5) out = true;
        f[d] = std::clamp(f[d], 0.0, static_cast<double>(n[d] - 1));
        i0[d] = std::min(static_cast<int>(std::floor(f[d])), std::max(0, n[d] - 2));
        w[d] = f[d] - i0[d];
        if (n[d] == 1) i0[d] = 0, w[d] = 0;
      }
      t.outside += out;
      double acc[3] = {0, 0, 0};
      for (int dz = 0; dz < 2; ++dz) {
        const double wz = dz ? w[2] : 1 - w[2];
        if (wz == 0) continue;
        const cv::Mat& img = cache.get(std::min(i0[2] + dz, nz - 1));
        for (int dy = 0; dy < 2; ++dy) {
          const double wy = dy ? w[1] : 1 - w[1];
          if (wy == 0) continue;
          const cv::Vec3b* row = img.ptr<cv::Vec3b>(std::min(i0[1] + dy, n[1] - 1));
          for (int dx = 0; dx < 2; ++dx) {
            const double wx = dx ? w[0] : 1 - w[0];
            if (wx == 0) continue;
            const cv::Vec3b& c = row[std::min(i0[0] + dx, n[0] - 1)];
            for (int ch = 0; ch < 3; ++ch) acc[ch] += wz * wy * wx * c[ch];  // (RGB)
          }
        }
      }
      std::uint8_t* px = &t.rgb[(static_cast<std::size_t>(b) * t.width + a) * 3];
      for (int ch = 0; ch < 3; ++ch) px[ch] = static_cast<std::uint8_t>(std::clamp(std::lround(acc[ch]), 0L, 255L));
    }
  }
  return t;
}

void write_texture_png(const std::string& path, const TextureImage& t) {
  cv::Mat rgb(t.height, t.width, CV_8UC3, const_cast<std::uint8_t*>(t.rgb.data())), bgr;
  cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
  AtomicFile out(path);
  if (!cv::imwrite(out.temp() + ".png", bgr)) throw Error(path, "cannot write the PNG texture");
  std::error_code ec;
  fs::rename(out.temp() + ".png", out.temp(), ec);
  if (ec) throw Error(path, "cannot write the PNG texture");
  out.commit();
}

}  // namespace orthosim
