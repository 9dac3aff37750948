# Run after flatnet_tests is built (CMakeLists.txt): one CTest entry per group of short test cases
# (tests/ctest_groups.hpp), "unit:<source file>", running that file's test cases not tagged [slow] or
# [solo] in one process. In:  TEST_EXECUTABLE, CTEST_FILE, TEST_PROPERTIES (every test entry's
# properties, as CMakeLists.txt sets them, space-separated).
execute_process(COMMAND "${TEST_EXECUTABLE}" --list-groups OUTPUT_VARIABLE groups RESULT_VARIABLE status)
if(NOT status EQUAL 0)
  message(FATAL_ERROR "${TEST_EXECUTABLE} --list-groups failed (exit ${status})")
endif()
string(STRIP "${groups}" groups)
string(REPLACE "\n" ";" groups "${groups}")
set(script "")
foreach(group IN LISTS groups)
  # -w NoTests: a group that matches no test case fails (exit 2) instead of passing empty.
  string(APPEND script
    "add_test([=[unit:${group}]=] [=[${TEST_EXECUTABLE}]=] [=[-#]=] -w NoTests [=[[#${group}]~[slow]~[solo]~[.]]=])\n"
    "set_tests_properties([=[unit:${group}]=] PROPERTIES LABELS unit ${TEST_PROPERTIES}"
    " ENVIRONMENT_MODIFICATION FLATNET_CTEST_GROUP=set:1)\n")
endforeach()
file(WRITE "${CTEST_FILE}" "${script}")
