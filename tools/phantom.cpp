// orthosim phantom --out DIR: writes a CVH-like colour cryosection stack of an
// upper limb with its exact ground truth (docs/phantom.md).
#include "libmodel/phantom/phantom.h"
#include "tools/common.h"

#include <iomanip>
#include <iostream>
#include <sstream>

namespace orthosim::cli {

void add_phantom_command(CLI::App& app) {
  auto* sub = app.add_subcommand(
      "phantom", "write a CVH-like colour slice stack of an upper limb with exact ground truth (truth.h5)");
  struct Args {
    std::string out;
    std::string size = "256x256x128";
    std::string spacing = "0.3,0.3,1.0";
    double noise = 4;
    bool jpeg = false;
    int jpeg_quality = 92;
    std::uint64_t seed = 1;
    CommonOptions common;
  };
  static Args a;
  sub->add_option("--out", a.out, "output directory (slices/, tissues.json, truth.h5)")->required();
  sub->add_option("--size", a.size, "voxels NXxNYxNZ (columns x rows x slices)")->capture_default_str();
  sub->add_option("--spacing", a.spacing, "voxel size in mm along x,y,z")->capture_default_str();
  sub->add_option("--noise", a.noise, "Gaussian sensor noise sigma, 8-bit units")->capture_default_str();
  sub->add_flag("--jpeg", a.jpeg, "write JPEG slices (with compression artefacts) instead of PNG");
  sub->add_option("--jpeg-quality", a.jpeg_quality, "JPEG quality 1..100")->capture_default_str();
  sub->add_option("--seed", a.seed, "seed of texture, illumination and noise")
      ->check(seed_check())->capture_default_str();
  add_common_options(sub, a.common);

  on_run(sub, "phantom", a.common, [] {
    PhantomOptions o;
    const std::vector<int> n = parse_size(a.size, 3, "--size");
    o.nx = n[0], o.ny = n[1], o.nz = n[2];
    const std::vector<double> s = parse_list(a.spacing, 3, "--spacing", true);
    for (int k = 0; k < 3; ++k) o.spacing_m[k] = s[k] * 1e-3;
    o.noise_sigma = a.noise;
    o.jpeg = a.jpeg;
    o.jpeg_quality = a.jpeg_quality;
    o.seed = a.seed;
    try {
      validate(o);
    } catch (const Error& e) {
      // name the flag: "phantom options: noise: ..." -> "--noise: ..."
      std::string m = e.message();
      const std::string prefix = "phantom options: ";
      if (m.rfind(prefix, 0) == 0) m = "--" + m.substr(prefix.size());
      if (m.rfind("--jpeg quality", 0) == 0) m = "--jpeg-quality" + m.substr(14);
      throw UsageError(m);
    }
    check_output_dir(a.out);

    Report report("phantom");
    report.parameters() = nlohmann::json::parse(phantom_parameters_json(o));
    report.parameters()["out"] = a.out;
    PhantomMetrics m;
    {
      Progress bar("phantom", o.nz, a.common.quiet);
      m = write_phantom(o, a.out, command_line(), [&](long done, long) { bar.update(done); });
    }
    report.phase("labels", m.labels_s);
    report.phase("slices", m.slices_s);
    report.phase("truth", m.truth_s);
    report.output(a.out);
    auto& j = report.metrics();
    j["voxels"] = m.voxels;
    j["surface_faces"] = m.surface_faces;
    j["vessel_nodes"] = m.vessel_nodes;
    j["slice_bytes"] = m.slice_bytes;
    report.write(a.common.report);
    if (!a.common.quiet) {
      std::ostringstream line;
      line << "phantom: wrote " << a.out << ": " << o.nz << " slices " << o.nx << "x" << o.ny << " ("
           << (o.jpeg ? "JPEG" : "PNG") << ", " << std::fixed << std::setprecision(1) << m.slice_bytes / 1e6
           << " MB), tissues.json, truth.h5 in " << std::setprecision(2) << m.labels_s + m.slices_s + m.truth_s
           << " s\n";
      std::cout << line.str();
    }
  });
}

}  // namespace orthosim::cli
