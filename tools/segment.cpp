// orthosim segment --stack DIR --tissues T.json --spacing X,Y,Z --out labels.h5:
// classifies a colour slice stack into the tissue table's labels
// (libmodel/segment/segment.h, docs/segment-surface.md).
#include "libmodel/format/model.h"
#include "libmodel/segment/segment.h"
#include "tools/common.h"

#include <sys/resource.h>
#include <tbb/global_control.h>

#include <array>
#include <iomanip>
#include <iostream>
#include <memory>
#include <set>
#include <sstream>

namespace orthosim::cli {

void add_segment_command(CLI::App& app) {
  auto* sub = app.add_subcommand("segment", "classify a colour slice stack into tissue labels (/volume)");
  struct Args {
    std::string stack, tissues, spacing, origin = "0,0,0", roi, slices, out, nrrd, truth, normalise = "plane", classify = "mahalanobis", scratch_dir,
                colour_space = "rgb";
    bool no_cleanup = false, no_order = false, no_fill_holes = false, exposure = false, register_slices = false;
    int register_window = 8;
    double register_max_shift = 32, register_min_response = 0.1;
    int speck_support = 2, calibration_slices = 9, refine_iterations = 8, slab = 8, threads = 0, bit_depth = 16;
    std::int64_t min_island = 64, min_vessel = 4;
    double min_island_mm3 = 20;
    double refine_max_shift = 30, lightness_weight = 1, min_body_fraction = 0.1;
    double smoothness = SegmentOptions{}.smoothness;
    int smoothing_sweeps = SegmentOptions{}.smoothing_sweeps;
    CommonOptions common;
  };
  static Args a;
  sub->add_option("--stack", a.stack, "folder of colour slices (png, jpg, tif, bmp), natural name order")
      ->required();
  sub->add_option("--tissues", a.tissues, "tissue table (tissues.json) with colour prototypes")->required();
  sub->add_option("--spacing", a.spacing, "voxel size in mm along x (columns), y (rows), z (slices)")->required();
  sub->add_option("--origin", a.origin, "position of voxel (0,0,0) in mm")->capture_default_str();
  sub->add_option("--roi", a.roi,
                  "segment only this part of the slices: X,Y,W,H in pixels (x columns, y rows, from the top left; "
                  "default: whole slices); --origin stays that of the slice files' pixel (0,0)");
  sub->add_option("--slices", a.slices,
                  "segment only the slices FIRST,LAST of the stack in natural name order, 0-based, inclusive (LAST -1: "
                  "to the last)");
  sub->add_option("--out", a.out, "output model file (writes /volume)")->required();
  sub->add_option("--nrrd", a.nrrd, "also write the labels as NRRD (3D Slicer)");
  sub->add_option("--truth", a.truth, "model file with a true /volume: per-tissue Dice in the report");
  sub->add_option("--normalise", a.normalise, "background normalisation: none, gain, plane")->capture_default_str();
  sub->add_option("--classify", a.classify,
                  "colour to prototype: mahalanobis (under the calibrated colour spread) or nearest (in --colour-space)")
      ->capture_default_str();
  sub->add_option("--colour-space", a.colour_space,
                  "space the colour calibration is fitted and colours are scored in: cielab or rgb (the 8-bit sRGB "
                  "values, where sensor noise is; docs/segment.md)")
      ->capture_default_str();
  sub->add_option("--smoothness", a.smoothness,
                  "smoothness prior: nats of colour evidence a voxel's label pays per unlike face neighbour (Potts, "
                  "26 neighbours weighted by distance; 0: off; mahalanobis only; docs/segment.md)")
      ->capture_default_str();
  sub->add_option("--smoothing-sweeps", a.smoothing_sweeps, "sweeps of the smoothness prior, 1..16")->capture_default_str();
  sub->add_flag("--no-cleanup", a.no_cleanup, "no clean-up at all (order, rank filter, components)");
  sub->add_flag("--no-order", a.no_order, "do not enforce the anatomical order of the table's 'inside'");
  sub->add_flag("--no-fill-holes", a.no_fill_holes, "keep background enclosed by the body");
  sub->add_option("--speck-support", a.speck_support, "like neighbours (of 26) a voxel needs to keep its label")
      ->capture_default_str();
  sub->add_option("--min-island", a.min_island, "smallest 3-D island of a bulk tissue kept, voxels (see --min-island-mm3)")
      ->capture_default_str();
  sub->add_option("--min-island-mm3", a.min_island_mm3,
                  "an island below --min-island voxels goes only if also below this volume (mm^3): coarse stacks keep "
                  "anatomy that size")
      ->capture_default_str();
  sub->add_option("--min-vessel", a.min_vessel, "smallest 3-D island of a vessel tissue kept, voxels")
      ->capture_default_str();
  sub->add_option("--min-body-fraction", a.min_body_fraction,
                  "keep body components of at least this fraction of the largest")
      ->capture_default_str();
  sub->add_option("--calibration-slices", a.calibration_slices, "slices used to calibrate the colours")
      ->capture_default_str();
  sub->add_option("--bit-depth", a.bit_depth,
                  "significant bits of 16-bit slices, 8..16 (12: a 12-bit camera's data in 16-bit files); "
                  "no effect on 8-bit slices")
      ->capture_default_str();
  sub->add_option("--refine-iterations", a.refine_iterations, "EM iterations of the colour calibration (0: table colours as they are)")
      ->capture_default_str();
  sub->add_option("--refine-max-shift", a.refine_max_shift, "largest prototype move by the calibration, CIE76 units")
      ->capture_default_str();
  sub->add_flag("--exposure-from-border", a.exposure,
                "scale the table's colours by the stack's exposure, read from a border of the table background's hue "
                "brighter or darker by more than 20 % (for a stack exposed darker or brighter as a whole; not for "
                "vignetted slices)");
  sub->add_flag("--register", a.register_slices,
                "undo the slices' jitter: each slice's shift against the one before by phase correlation, the stack's "
                "smooth drift kept (a line over 2 x --register-window + 1 slices), the rest undone in whole pixels");
  sub->add_option("--register-window", a.register_window, "--register: slices each side of the drift's local line")
      ->capture_default_str();
  sub->add_option("--register-max-shift", a.register_max_shift,
                  "--register: a slice-to-slice shift beyond this many pixels is taken as none (another structure's match)")
      ->capture_default_str();
  sub->add_option("--register-min-response", a.register_min_response,
                  "--register: a slice-to-slice match whose phase-correlation peak (0..1) is below this is not used")
      ->capture_default_str();
  sub->add_option("--lightness-weight", a.lightness_weight, "weight of lightness against chroma (cielab)")
      ->capture_default_str();
  sub->add_option("--slab", a.slab, "slices classified together (memory ~ slab x slice size)")
      ->capture_default_str();
  sub->add_option("--scratch-dir", a.scratch_dir, "folder for the scratch file of large stacks (default: temp)");
  sub->add_option("--threads", a.threads, "worker threads (0: all cores)")->capture_default_str();
  add_common_options(sub, a.common);

  on_run(sub, "segment", a.common, [] {
    SegmentOptions o;
    const std::vector<double> s = parse_list(a.spacing, 3, "--spacing", true);
    const std::vector<double> org = parse_list(a.origin, 3, "--origin", false);
    check_voxel_flags(s, org);
    for (int k = 0; k < 3; ++k) o.spacing_m[k] = s[k] * 1e-3, o.origin_m[k] = org[k] * 1e-3;
    parse_roi_flags(a.roi, a.slices, o);
    if (a.normalise == "none") o.normalise = SegmentOptions::Normalise::none;
    else if (a.normalise == "gain") o.normalise = SegmentOptions::Normalise::gain;
    else if (a.normalise == "plane") o.normalise = SegmentOptions::Normalise::plane;
    else throw UsageError("--normalise: expected none, gain or plane, got '" + a.normalise + "'");
    if (a.classify == "mahalanobis") o.classify = SegmentOptions::Classify::mahalanobis;
    else if (a.classify == "nearest") o.classify = SegmentOptions::Classify::nearest;
    else throw UsageError("--classify: expected mahalanobis or nearest, got '" + a.classify + "'");
    if (a.colour_space == "cielab") o.colour_space = SegmentOptions::Space::cielab;
    else if (a.colour_space == "rgb") o.colour_space = SegmentOptions::Space::rgb;
    else throw UsageError("--colour-space: expected cielab or rgb, got '" + a.colour_space + "'");
    o.smoothness = a.smoothness;
    o.smoothing_sweeps = a.smoothing_sweeps;
    o.cleanup = !a.no_cleanup;
    o.enforce_order = !a.no_order;
    o.fill_holes = !a.no_fill_holes;
    o.speck_support = a.speck_support;
    o.min_island_voxels = a.min_island;
    o.min_island_mm3 = a.min_island_mm3;
    o.min_vessel_voxels = a.min_vessel;
    o.min_body_fraction = a.min_body_fraction;
    o.calibration_slices = a.calibration_slices;
    o.bit_depth = a.bit_depth;
    o.refine_iterations = a.refine_iterations;
    o.refine_max_shift = a.refine_max_shift;
    o.exposure_from_border = a.exposure;
    o.register_slices = a.register_slices;
    o.registration.half_window = a.register_window;
    o.registration.max_shift_px = a.register_max_shift;
    o.registration.min_response = a.register_min_response;
    o.lightness_weight = a.lightness_weight;
    o.slab = a.slab;
    o.scratch_dir = a.scratch_dir;
    try {
      validate(o);
    } catch (const Error& e) {
      throw UsageError("--" + e.message());  // (the spacing and origin were checked above, as flags)
    }
    if (a.threads < 0) throw UsageError("--threads: must be >= 0");
    std::unique_ptr<tbb::global_control> threads;
    if (a.threads > 0)
      threads = std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, a.threads);

    // inputs first: nothing is written unless all of them are good
    const TissueTable table = load_tissue_table(a.tissues);
    require_background_colour(table);
    check_output_file(a.out);
    if (!a.nrrd.empty()) check_output_file(a.nrrd);
    std::array<int, 3> truth_offset{0, 0, 0};
    if (!a.truth.empty()) {
      // the truth must match the stack (or the region of interest) voxel for
      // voxel: checked here, since the Dice comes after --out is written
      // (segment_stack checks the region itself before it writes anything)
      const SliceSource whole = stack_source(a.stack, a.bit_depth);
      const SliceSource part = roi_source(whole, o);
      ModelReader truth(a.truth);
      const std::string ds = "/volume/labels";
      if (!truth.has(ds)) throw Error(a.truth, "missing dataset /volume/labels (no truth volume)");
      if (!truth.h5().has_attr("/volume", "label_names")) throw Error(a.truth, "/volume has no label_names");
      const auto d = truth.h5().dims(ds);
      auto dims = [](const SliceSource& q) {
        return std::vector<std::uint64_t>{static_cast<std::uint64_t>(q.nz), static_cast<std::uint64_t>(q.ny),
                                          static_cast<std::uint64_t>(q.nx)};
      };
      if (d == dims(whole) && d != dims(part)) truth_offset = roi_offset(o);  // the whole stack's truth
      else if (d != dims(part)) {
        std::ostringstream m;
        m << "truth volume is ";
        for (std::size_t k = d.size(); k-- > 0;) m << d[k] << (k ? "x" : "");
        m << " voxels, the stack " << a.stack << " is " << whole.nx << "x" << whole.ny << "x" << whole.nz;
        if (has_roi(o)) m << " and its region of interest " << part.nx << "x" << part.ny << "x" << part.nz;
        throw Error(a.truth, m.str());
      }
    }

    Report report("segment");
    // the slices segment reads (hash_stack): a note or a hidden file beside
    // them, or a slice outside --slices, is no input (the whole folder's hash
    // read every file of a full-body stack, and went into the provenance)
    report.input(a.stack, hash_stack(a.stack, o.first_slice, o.last_slice));
    report.input(a.tissues);
    report.parameters() = nlohmann::json::parse(segment_parameters_json(o));
    report.parameters()["threads"] = a.threads;

    SegmentFiles f;
    f.stack_dir = a.stack;
    f.tissues_path = a.tissues;
    f.out_h5 = a.out;
    f.nrrd_path = a.nrrd;
    f.command_line = command_line();
    f.inputs_json = report.json()["inputs"].dump();
    SegmentMetrics m;
    {
      Progress bar("segment", 1, a.common.quiet);
      m = segment_stack(f, table, o, [&](long done, long total) {
        (void)total;
        bar.update(done);
      });
    }
    report.phase("calibrate", m.calibrate_s);
    report.phase("classify", m.classify_s);
    report.phase("cleanup", m.cleanup_s);
    report.phase("components", m.components_s);
    report.phase("write", m.write_s);
    report.output(a.out);
    if (!a.nrrd.empty()) report.output(a.nrrd);
    auto& j = report.metrics();
    const double voxels = static_cast<double>(m.nx) * m.ny * m.nz;
    j["size"] = {m.nx, m.ny, m.nz};
    j["stack_size"] = m.stack_size;
    j["stack_offset_voxels"] = roi_offset(o);
    j["bit_depth"] = a.bit_depth;
    if (!m.stack_note.empty()) {
      j["stack_note"] = m.stack_note;
      std::cerr << "orthosim segment: warning: " << a.stack << ": " << m.stack_note << "\n";
    }
    j["voxels"] = m.voxels;
    j["read_cpu_s"] = m.read_s;
    j["voxels_per_s"] = voxels / std::max(1e-9, m.calibrate_s + m.classify_s + m.cleanup_s + m.components_s +
                                                     m.write_s);
    nlohmann::json protos = nlohmann::json::array();
    const auto names = table.label_names();
    auto name_of = [&](int l) { return l >= 0 && l < static_cast<int>(names.size()) ? names[l] : std::string(); };
    const std::vector<int> nearer = nearest_table_labels(m.prototypes);
    auto cie76 = [](const std::array<double, 3>& x, const std::array<double, 3>& y) {
      return std::sqrt((x[0] - y[0]) * (x[0] - y[0]) + (x[1] - y[1]) * (x[1] - y[1]) + (x[2] - y[2]) * (x[2] - y[2]));
    };
    {
      nlohmann::json sep = nlohmann::json::array();
      for (const auto& s : m.separations)
        sep.push_back({{"tissues", {name_of(s.a), name_of(s.b)}}, {"delta", s.delta},
                       {"confusion", 0.5 * std::erfc(s.delta / (2 * std::sqrt(2.0)))}});
      j["separations"] = sep;
    }
    for (std::size_t k = 0; k < m.prototypes.size(); ++k) {
      const Prototype& p = m.prototypes[k];
      const double d = cie76(p.lab, p.table_lab);
      protos.push_back({{"tissue", name_of(p.label)},
                        {"table_lab", p.table_lab},
                        {"lab", p.lab},
                        {"pixel_lab", p.pixel_lab},
                        {"shift", d},
                        {"samples", p.samples},
                        {"nearest_table_colour", name_of(nearer[k])}});
      if (nearer[k] != p.label)  // even with --quiet: the labels of both tissues may be wrong
        std::cerr << "orthosim segment: warning: " << a.stack << ": the calibrated colour of '" << name_of(p.label)
                  << "' moved " << std::lround(d) << " CIE76 units from its table colour, nearer the table colour of '"
                  << name_of(nearer[k]) << "' than its own: it may have taken that tissue's pixels, or the table's "
                  << "colour is far off (" << a.tissues << "; --refine-iterations 0 keeps the table's colours)\n";
    }
    j["prototypes"] = protos;
    // two tissues whose table colours a person could not tell apart: the stack cannot
    // either, and their voxels are split between them (a 'tendon' 1 unit of red from
    // the muscle took a quarter of it, exit 0; sweep of 2026-11-27). The bound is a
    // just-noticeable difference in CIE76 (Sharma, Digital Color Imaging Handbook).
    {
      constexpr double kJnd = 2.3;
      std::set<std::pair<int, int>> told;
      for (std::size_t k = 0; k < m.prototypes.size(); ++k)
        for (std::size_t l = k + 1; l < m.prototypes.size(); ++l) {
          const Prototype &p = m.prototypes[k], &q = m.prototypes[l];
          if (p.label == q.label) continue;
          const double d = cie76(p.table_lab, q.table_lab);
          if (d >= kJnd || !told.insert({std::min(p.label, q.label), std::max(p.label, q.label)}).second) continue;
          std::cerr << "orthosim segment: warning: " << a.tissues << ": the table colours of '" << name_of(p.label)
                    << "' and '" << name_of(q.label) << "' are " << std::setprecision(2) << d
                    << " CIE76 units apart, below a just-noticeable difference (" << kJnd
                    << "): the stack cannot tell them apart and their voxels are split between them\n";
        }
    }
    // a tissue whose colour the calibration found (samples) with no voxel left: the
    // clean-up gave them away, or the classifier did (a palette stack: the muscle's
    // 12 000 samples, none of its voxels). pipeline refuses it; alone, segment warns.
    {
      std::map<std::string, std::int64_t> samples;
      for (const Prototype& p : m.prototypes) samples[name_of(p.label)] += p.samples;
      for (const auto& [tissue, n] : samples) {
        const auto v = m.voxels.find(tissue);
        if (n > 0 && (v == m.voxels.end() || v->second == 0))
          std::cerr << "orthosim segment: warning: " << a.stack << ": no voxel of '" << tissue
                    << "' is left, though the calibration found its colour (" << n
                    << " samples): the classifier or the clean-up gave its voxels to other tissues (check its "
                    << "colours and 'inside' in " << a.tissues << ")" << colour_noise_note(j["separations"], tissue)
                    << "\n";
      }
      // The calibration samples are a grid over slices spread along the stack, so
      // each tissue's share of them and of the labelled voxels agree (within 0.01
      // on the phantoms up to noise 28; within 6x for rare tissues on the real
      // crop, whose clean-up moves its shaded fat). A collapsed calibration breaks
      // that: at noise 32 the vein's prototype took 10 % of the samples and then
      // 58 % of the voxels, the gel's 52 % of the samples 3 % (exit 0, and the
      // pipeline stopped later in surface with a line about the muscle). Said
      // where a tissue holds a fifth of either and the shares differ 4-fold.
      double all_samples = 0, all_voxels = 0;
      for (const auto& [tissue, n] : samples) all_samples += static_cast<double>(n);
      for (const auto& [tissue, n] : m.voxels) all_voxels += static_cast<double>(n);
      nlohmann::json disagree = nlohmann::json::array();
      for (const auto& [tissue, n] : samples) {
        const auto v = m.voxels.find(tissue);
        const double sf = n / std::max(all_samples, 1.0);
        const double vf = (v == m.voxels.end() ? 0.0 : static_cast<double>(v->second)) / std::max(all_voxels, 1.0);
        if (std::max(sf, vf) < 0.2 || (vf <= 4 * sf && sf <= 4 * vf)) continue;
        disagree.push_back({{"tissue", tissue}, {"sample_fraction", sf}, {"voxel_fraction", vf}});
        // the embedding medium's colour found, its voxels gone: the body's outline
        // enclosed it (a whole cryosection photograph: its dark frame taken for
        // muscle around the gel, the gel then filled as muscle; 30 % of the samples,
        // 0 % of the voxels)
        const bool enclosed = tissue == name_of(0) && vf < sf;
        std::cerr << "orthosim segment: warning: " << a.stack << ": '" << tissue << "' has " << std::lround(100 * vf)
                  << " % of the voxels but " << std::lround(100 * sf)
                  << " % of the calibration samples: the labels disagree with the colour calibration, which has "
                     "probably collapsed (noise too strong for the table's colours to be told apart, or the table's "
                     "colours far off; "
                  << a.tissues << ")"
                  << (enclosed ? ", or something around the specimen that the table does not name (the photograph's "
                                 "frame, a scale, a label) was taken for tissue and the body's outline enclosed the "
                                 "embedding medium: segment a --roi around the specimen"
                               : "")
                  << "\n";
      }
      j["calibration_disagreements"] = disagree;
    }
    j["exposure"] = m.exposure;
    if (a.register_slices) {
      const SliceRegistration& g = m.registration;
      j["registration"] = {{"shift_px", g.shift},       {"pairwise_px", g.pairwise}, {"response", g.response},
                           {"moved_slices", g.moved},   {"rejected_pairs", g.rejected},
                           {"max_shift_px", g.max_shift_px}, {"min_response", g.min_response}, {"seconds", g.seconds},
                           {"weak_slices", g.weak}};
      // even with --quiet: where the slices did not match, they were not registered
      if (!g.weak.empty()) {
        std::string list;
        for (std::size_t k = 0; k < g.weak.size() && k < 8; ++k) list += (k ? ", " : "") + std::to_string(g.weak[k]);
        if (g.weak.size() > 8) list += ", ...";
        std::cerr << "orthosim segment: warning: " << a.stack << ": --register: " << g.weak.size()
                  << " slice(s) match the one before too weakly to be placed by it (phase-correlation peak below "
                  << a.register_min_response << ", or a shift beyond --register-max-shift; slices " << list
                  << "): the slices may lie too far apart for their detail, and those are registered only through "
                     "their other neighbours\n";
      }
    }
    j["gain_min"] = m.gain_min;
    j["gain_max"] = m.gain_max;
    j["normalise_fallbacks"] = m.normalise_fallbacks;
    j["cleanup"] = {{"smooth_changed", m.smooth_changed}, {"order_changed", m.order_changed},     {"speck_changed", m.speck_changed},
                    {"holes_filled", m.holes_filled},       {"islands_absorbed", m.islands_absorbed}, {"misplaced_absorbed", m.misplaced_absorbed},
                    {"detached_removed", m.detached_removed}, {"components", m.components},
                    {"body_components", m.body_components}};
    j["scratch_bytes"] = m.scratch_bytes;
    j["scratch_spilled"] = m.scratch_spilled;
    rusage ru{};
    getrusage(RUSAGE_SELF, &ru);
    j["peak_rss_mib"] = static_cast<double>(ru.ru_maxrss) / 1024.0;
    if (!a.truth.empty()) {
      Phase p(report, "dice");
      std::map<std::string, std::int64_t> tv;
      j["dice"] = dice_per_tissue(a.out, a.truth, &tv, truth_offset);
      j["truth_voxels"] = tv;
      // a tissue the truth does not name has no Dice: said, not left out silently
      // (a table naming the skin 'dermis' reported a perfect Dice of the rest; sweep
      // of 2026-11-27)
      std::vector<std::string> unmatched;
      for (const Tissue& t : table.tissues)
        if (!j["dice"].contains(t.name) && m.voxels.count(t.name) && m.voxels.at(t.name) > 0) unmatched.push_back(t.name);
      if (!unmatched.empty()) {
        std::string list;
        for (const auto& n : unmatched) list += (list.empty() ? "'" : ", '") + n + "'";
        std::cerr << "orthosim segment: warning: " << a.truth << ": no tissue of that name in the truth for " << list
                  << ": no Dice for them (the truth names its labels itself)\n";
        j["dice_missing"] = unmatched;
      }
    }
    report.write(a.common.report);
    if (!a.common.quiet) {
      std::ostringstream line;
      line << "segment: wrote " << a.out << ": " << m.nx << "x" << m.ny << "x" << m.nz << " voxels in " << std::fixed
           << std::setprecision(2) << report.json()["wall_s"].get<double>() << " s (" << std::setprecision(1)
           << j["voxels_per_s"].get<double>() / 1e6 << " M voxels/s)";
      if (j.contains("dice")) {
        line << ", Dice";
        for (const auto& [k, v] : j["dice"].items()) line << " " << k << " " << std::setprecision(3) << v.get<double>();
      }
      std::cout << line.str() << "\n";
    }
  });
}

}  // namespace orthosim::cli
