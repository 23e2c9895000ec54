// Strict JSON parsing shared by the scene and tissue-table readers.
#pragma once

#include <nlohmann/json.hpp>

#include <set>
#include <string>
#include <vector>

namespace orthosim {

// Parses `text` like nlohmann::json::parse (throwing its parse_error), and
// sets `twice` to the first key that appears twice in one object ("" when
// none). JSON leaves such a key undefined and the parser keeps the last one:
// {"dt": 0.01, "dt": 0.02} ran at 0.02, silently.
inline nlohmann::json parse_json_noting_repeats(const std::string& text, std::string& twice) {
  using json = nlohmann::json;
  std::vector<std::set<std::string>> keys;
  twice.clear();
  const json::parser_callback_t on = [&](int, json::parse_event_t ev, json& parsed) {
    if (ev == json::parse_event_t::object_start) keys.emplace_back();
    else if (ev == json::parse_event_t::object_end && !keys.empty()) keys.pop_back();
    else if (ev == json::parse_event_t::key && !keys.empty() && !keys.back().insert(parsed.get<std::string>()).second &&
             twice.empty())
      twice = parsed.get<std::string>();
    return true;
  };
  return json::parse(text, on);
}

}  // namespace orthosim
