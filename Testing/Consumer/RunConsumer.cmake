# cmake -P driver of the consumer.* tests: configures, builds and runs Testing/Consumer/Project,
# an out-of-tree project written exactly as README's "VTK C++" section, against SIPMSS
#   MODE=build-tree : the build tree, CMAKE_PREFIX_PATH=<build dir> (as README says);
#   MODE=install    : `cmake --install <build dir> --prefix <tmp>`, the prefix then moved to another
#                     path (relocatable), CMAKE_PREFIX_PATH=<moved prefix>.
# Everything goes under WORK_DIR, which is removed at the end, pass or fail.
#
# Variables: MODE, SIPMSS_BINARY_DIR, SIPMSS_SOURCE_DIR, PROJECT_DIR, WORK_DIR, GENERATOR,
# VTK_DIR (the VTK SIPMSS was built against), MAKE_PROGRAM, CXX_COMPILER, BUILD_TYPE; RUN_LIBRARY_PATH (VTK's library directory when the loader
# does not search it: put into LD_LIBRARY_PATH for running the consumer only).
cmake_minimum_required(VERSION 3.16)

foreach (_var IN ITEMS MODE SIPMSS_BINARY_DIR SIPMSS_SOURCE_DIR PROJECT_DIR WORK_DIR GENERATOR
    VTK_DIR CXX_COMPILER BUILD_TYPE)
  if (NOT DEFINED ${_var} OR "${${_var}}" STREQUAL "")
    message(FATAL_ERROR "RunConsumer.cmake: ${_var} is not set")
  endif ()
endforeach ()
if (NOT MODE MATCHES "^(build-tree|install)$")
  message(FATAL_ERROR "RunConsumer.cmake: MODE must be build-tree or install, not '${MODE}'")
endif ()

# Only what the command line gives: no prefix path or VTK_DIR from the caller's environment.
unset(ENV{CMAKE_PREFIX_PATH})
unset(ENV{VTK_DIR})
unset(ENV{SIPMSS_DIR})
unset(ENV{ParaView_DIR})
unset(ENV{LD_LIBRARY_PATH})
set(ENV{CMAKE_BUILD_PARALLEL_LEVEL} 2)

set(_failure "")

# Runs a command; on failure records the message and the command's output in _failure.
macro (_run what)
  execute_process(COMMAND ${ARGN}
    RESULT_VARIABLE _rc OUTPUT_VARIABLE _out ERROR_VARIABLE _out)
  if (NOT _rc EQUAL 0)
    string(REPLACE ";" " " _cmd "${ARGN}")
    set(_failure "${what} failed (${_rc}):\n  ${_cmd}\n${_out}")
  else ()
    message(STATUS "${what}: ok")
  endif ()
endmacro ()

# Configures, builds and runs the consumer against the SIPMSS package under `prefix`; checks that
# it found SIPMSSConfig.cmake in `expected_dir`.
function (_consume prefix expected_dir build_dir)
  set(_failure "")
  set(_make_program)
  if (MAKE_PROGRAM)
    set(_make_program "-DCMAKE_MAKE_PROGRAM=${MAKE_PROGRAM}")
  endif ()
  _run("configure the consumer with CMAKE_PREFIX_PATH=${prefix}"
    "${CMAKE_COMMAND}" -S "${PROJECT_DIR}" -B "${build_dir}" -G "${GENERATOR}" ${_make_program}
    "-DCMAKE_CXX_COMPILER=${CXX_COMPILER}" "-DCMAKE_BUILD_TYPE=${BUILD_TYPE}"
    "-DCMAKE_PREFIX_PATH=${prefix}")
  if (NOT _failure)
    file(STRINGS "${build_dir}/CMakeCache.txt" _dir REGEX "^SIPMSS_DIR:")
    string(REGEX REPLACE "^SIPMSS_DIR:[A-Z]+=" "" _dir "${_dir}")
    get_filename_component(_dir "${_dir}" REALPATH)
    get_filename_component(_expected "${expected_dir}" REALPATH)
    if (NOT _dir STREQUAL _expected)
      set(_failure "the consumer found SIPMSS in '${_dir}', not in '${_expected}'")
    endif ()
  endif ()
  if (NOT _failure)
    _run("build the consumer" "${CMAKE_COMMAND}" --build "${build_dir}" --parallel 2)
  endif ()
  if (NOT _failure)
    set(_env)
    if (RUN_LIBRARY_PATH)
      set(_env "${CMAKE_COMMAND}" -E env "LD_LIBRARY_PATH=${RUN_LIBRARY_PATH}")
    endif ()
    _run("run the consumer" ${_env} "${build_dir}/app")
    if (NOT _failure)
      message(STATUS "  ${_out}")
    endif ()
  endif ()
  set(_failure "${_failure}" PARENT_SCOPE)
endfunction ()

file(REMOVE_RECURSE "${WORK_DIR}")
file(MAKE_DIRECTORY "${WORK_DIR}")

if (MODE STREQUAL "build-tree")
  file(GLOB _config "${SIPMSS_BINARY_DIR}/lib*/cmake/SIPMSS/SIPMSSConfig.cmake")
  if (NOT _config)
    set(_failure "no SIPMSSConfig.cmake below ${SIPMSS_BINARY_DIR}/lib*/cmake/SIPMSS")
  else ()
    get_filename_component(_config_dir "${_config}" DIRECTORY)
    _consume("${SIPMSS_BINARY_DIR}" "${_config_dir}" "${WORK_DIR}/consumer")
  endif ()
else ()
  set(_prefix "${WORK_DIR}/prefix")
  _run("cmake --install into ${_prefix}"
    "${CMAKE_COMMAND}" --install "${SIPMSS_BINARY_DIR}" --prefix "${_prefix}")
  if (NOT _failure)
    # The package, its headers and the filter library are installed.
    file(GLOB_RECURSE _installed RELATIVE "${_prefix}" "${_prefix}/*")
    list(SORT _installed)
    string(REPLACE ";" "\n  " _listing "${_installed}")
    message(STATUS "installed:\n  ${_listing}")
    foreach (_pattern IN ITEMS
        "/cmake/SIPMSS/SIPMSSConfig.cmake$" "/cmake/SIPMSS/SIPMSSConfigVersion.cmake$"
        "/cmake/SIPMSS/SIPMSS-targets.cmake$" "/cmake/SIPMSS/SIPMSS-vtk-module-properties.cmake$"
        "^include/sipmss/vtkSIPMSSDecimate.h$" "^include/sipmss/vtkSIPMSSCluster.h$"
        "^include/sipmss/vtkSIPMSSFilterBase.h$" "^include/sipmss/sipmssFiltersModule.h$"
        "/libsipmssFilters[^/]*\\.so")
      set(_match "${_installed}")
      list(FILTER _match INCLUDE REGEX "${_pattern}")
      if (NOT _match)
        set(_failure "nothing installed matches '${_pattern}'")
        break ()
      endif ()
    endforeach ()
  endif ()
  if (NOT _failure)
    # Relocatable: no installed CMake file names the build tree, the sources or the prefix (the
    # VTK it depends on may be named: the vtk preset's lives in the source tree).
    file(GLOB_RECURSE _cmake_files "${_prefix}/*.cmake")
    foreach (_file IN LISTS _cmake_files)
      file(READ "${_file}" _text)
      string(REPLACE "${VTK_DIR}" "<VTK_DIR>" _text "${_text}")
      foreach (_path IN ITEMS "${SIPMSS_BINARY_DIR}" "${SIPMSS_SOURCE_DIR}" "${_prefix}")
        string(FIND "${_text}" "${_path}" _at)
        if (NOT _at EQUAL -1)
          set(_failure "installed ${_file} names ${_path}: the prefix is not relocatable")
          break ()
        endif ()
      endforeach ()
      if (_failure)
        break ()
      endif ()
    endforeach ()
  endif ()
  if (NOT _failure)
    set(_moved "${WORK_DIR}/moved/elsewhere")
    file(MAKE_DIRECTORY "${WORK_DIR}/moved")
    file(RENAME "${_prefix}" "${_moved}")
    file(GLOB _config "${_moved}/lib*/cmake/SIPMSS/SIPMSSConfig.cmake")
    get_filename_component(_config_dir "${_config}" DIRECTORY)
    _consume("${_moved}" "${_config_dir}" "${WORK_DIR}/consumer")
  endif ()
endif ()

file(REMOVE_RECURSE "${WORK_DIR}")
if (_failure)
  message(FATAL_ERROR "${_failure}")
endif ()
