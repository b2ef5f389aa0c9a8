# add_fmu(): compile a C model into a shared library and pack it as an FMI 2.0 FMU.
#
#   add_fmu(TARGET <name>                     # target that builds the .fmu (library: <name>_binary)
#           [MODEL_DIR <dir>]                 # folder with modelDescription.xml (+ config.h, model.c)
#           [MODEL_DESCRIPTION <file>]        # default: <MODEL_DIR>/modelDescription.xml
#           [MODEL_IDENTIFIER <id>]           # default: read from the modelDescription.xml
#           [FMU_NAME <file.fmu>]             # default: <name>.fmu
#           [OUTPUT_DIR <dir>]                # default: ${CMAKE_BINARY_DIR}/fmus
#           [SOURCES <c files>]               # default: <MODEL_DIR>/model.c + the shared FMI glue
#           [EXTRA_SOURCES <c files>]         # compiled in addition to SOURCES
#           [HEADERS <h files>]               # shipped in sources/ (default: config.h + model.h)
#           [INCLUDE_DIRS <dirs>] [DEFINITIONS <defs>] [LINK_LIBRARIES <libs>]
#           [RESOURCES <files or dirs>])      # copied into resources/
#
# The FMU holds modelDescription.xml, binaries/<platform>/<id>.<ext> and sources/. Only the
# fmi2* functions are exported: everything else is compiled with hidden visibility.
include_guard(GLOBAL)

set(FMUBUILDER_EXAMPLES_COMMON_DIR "${CMAKE_CURRENT_LIST_DIR}/../examples/common")
get_filename_component(FMUBUILDER_EXAMPLES_COMMON_DIR "${FMUBUILDER_EXAMPLES_COMMON_DIR}" ABSOLUTE)

# The FMI 2.0 headers: fmpy ships them, so ask the Python that has fmpy installed.
if(NOT FMI_HEADERS_DIR)
  find_package(Python3 COMPONENTS Interpreter QUIET)
  if(Python3_Interpreter_FOUND)
    execute_process(
      COMMAND "${Python3_EXECUTABLE}" -c
              "import fmpy, os; print(os.path.join(os.path.dirname(fmpy.__file__), 'c-code'))"
      OUTPUT_VARIABLE _fmpy_c_code
      OUTPUT_STRIP_TRAILING_WHITESPACE
      RESULT_VARIABLE _fmpy_result
      ERROR_QUIET)
    if(_fmpy_result EQUAL 0 AND EXISTS "${_fmpy_c_code}/fmi2Functions.h")
      set(_fmi_headers_default "${_fmpy_c_code}")
    endif()
  endif()
endif()
set(FMI_HEADERS_DIR "${_fmi_headers_default}" CACHE PATH "Directory containing fmi2Functions.h")
if(NOT EXISTS "${FMI_HEADERS_DIR}/fmi2Functions.h")
  message(FATAL_ERROR
    "fmi2Functions.h not found (FMI_HEADERS_DIR='${FMI_HEADERS_DIR}'). "
    "Install fmpy for the Python on PATH or pass -DFMI_HEADERS_DIR=<dir with the FMI 2.0 headers>.")
endif()

# binaries/<platform> folder name of the FMI 2.0 standard.
if(CMAKE_SIZEOF_VOID_P EQUAL 8)
  set(_fmi_bits 64)
else()
  set(_fmi_bits 32)
endif()
if(WIN32)
  set(FMI_PLATFORM "win${_fmi_bits}")
elseif(APPLE)
  set(FMI_PLATFORM "darwin${_fmi_bits}")
else()
  set(FMI_PLATFORM "linux${_fmi_bits}")
endif()

function(_fmu_read_model_identifier xml_file out_var)
  file(READ "${xml_file}" _xml)
  string(REGEX MATCH "<ModelExchange[^>]*modelIdentifier=\"([^\"]+)\"" _match "${_xml}")
  if(NOT _match)
    message(FATAL_ERROR "${xml_file}: no <ModelExchange modelIdentifier=\"...\"> found.")
  endif()
  set(${out_var} "${CMAKE_MATCH_1}" PARENT_SCOPE)
endfunction()

function(_fmu_absolute_paths out_var)
  set(_result "")
  foreach(_path IN LISTS ARGN)
    get_filename_component(_abs "${_path}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
    list(APPEND _result "${_abs}")
  endforeach()
  set(${out_var} "${_result}" PARENT_SCOPE)
endfunction()

function(add_fmu)
  cmake_parse_arguments(FMU ""
    "TARGET;MODEL_DIR;MODEL_DESCRIPTION;MODEL_IDENTIFIER;FMU_NAME;OUTPUT_DIR"
    "SOURCES;EXTRA_SOURCES;HEADERS;INCLUDE_DIRS;DEFINITIONS;LINK_LIBRARIES;RESOURCES"
    ${ARGN})
  if(FMU_UNPARSED_ARGUMENTS)
    message(FATAL_ERROR "add_fmu: unknown arguments: ${FMU_UNPARSED_ARGUMENTS}")
  endif()
  if(NOT FMU_TARGET)
    message(FATAL_ERROR "add_fmu: TARGET is required.")
  endif()
  if(FMU_MODEL_DIR)
    get_filename_component(FMU_MODEL_DIR "${FMU_MODEL_DIR}" ABSOLUTE
                           BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
  endif()
  if(NOT FMU_MODEL_DESCRIPTION)
    if(NOT FMU_MODEL_DIR)
      message(FATAL_ERROR "add_fmu(${FMU_TARGET}): give MODEL_DIR or MODEL_DESCRIPTION.")
    endif()
    set(FMU_MODEL_DESCRIPTION "${FMU_MODEL_DIR}/modelDescription.xml")
  endif()
  _fmu_absolute_paths(FMU_MODEL_DESCRIPTION ${FMU_MODEL_DESCRIPTION})

  _fmu_read_model_identifier("${FMU_MODEL_DESCRIPTION}" _xml_identifier)
  if(NOT FMU_MODEL_IDENTIFIER)
    set(FMU_MODEL_IDENTIFIER "${_xml_identifier}")
  elseif(NOT FMU_MODEL_IDENTIFIER STREQUAL _xml_identifier)
    message(FATAL_ERROR "add_fmu(${FMU_TARGET}): MODEL_IDENTIFIER '${FMU_MODEL_IDENTIFIER}' "
                        "differs from '${_xml_identifier}' in ${FMU_MODEL_DESCRIPTION}.")
  endif()

  # Default layout of an example model: physics in model.c, FMI in the shared glue.
  if(NOT FMU_SOURCES)
    set(FMU_SOURCES "${FMU_MODEL_DIR}/model.c" "${FMUBUILDER_EXAMPLES_COMMON_DIR}/fmi2_glue.c")
    if(NOT FMU_HEADERS)
      set(FMU_HEADERS "${FMU_MODEL_DIR}/config.h" "${FMUBUILDER_EXAMPLES_COMMON_DIR}/model.h")
    endif()
    list(APPEND FMU_INCLUDE_DIRS "${FMU_MODEL_DIR}" "${FMUBUILDER_EXAMPLES_COMMON_DIR}")
  endif()
  _fmu_absolute_paths(_sources ${FMU_SOURCES} ${FMU_EXTRA_SOURCES})
  _fmu_absolute_paths(_headers ${FMU_HEADERS})
  _fmu_absolute_paths(_resources ${FMU_RESOURCES})
  _fmu_absolute_paths(_include_dirs ${FMU_INCLUDE_DIRS})

  if(NOT FMU_FMU_NAME)
    set(FMU_FMU_NAME "${FMU_TARGET}.fmu")
  endif()
  if(NOT FMU_OUTPUT_DIR)
    set(FMU_OUTPUT_DIR "${CMAKE_BINARY_DIR}/fmus")
  endif()
  set(_fmu_file "${FMU_OUTPUT_DIR}/${FMU_FMU_NAME}")
  set(_staging "${CMAKE_CURRENT_BINARY_DIR}/fmu_staging/${FMU_TARGET}")

  # The shared library, named exactly like the modelIdentifier (no "lib" prefix).
  set(_library "${FMU_TARGET}_binary")
  add_library(${_library} SHARED ${_sources})
  set_target_properties(${_library} PROPERTIES
    PREFIX ""
    OUTPUT_NAME "${FMU_MODEL_IDENTIFIER}"
    LIBRARY_OUTPUT_DIRECTORY "${CMAKE_CURRENT_BINARY_DIR}/fmu_libraries/${FMU_TARGET}"
    C_VISIBILITY_PRESET hidden
    CXX_VISIBILITY_PRESET hidden
    VISIBILITY_INLINES_HIDDEN ON)
  target_include_directories(${_library} PRIVATE ${_include_dirs} "${FMI_HEADERS_DIR}")
  target_compile_definitions(${_library} PRIVATE ${FMU_DEFINITIONS})
  if(NOT MSVC)
    target_compile_options(${_library} PRIVATE -Wall -Wextra)
  endif()
  if(UNIX)
    target_link_libraries(${_library} PRIVATE m)
  endif()
  if(FMU_LINK_LIBRARIES)
    target_link_libraries(${_library} PRIVATE ${FMU_LINK_LIBRARIES})
  endif()

  # Pack: a fresh staging folder each time, so removed sources never linger in the FMU.
  set(_binaries "${_staging}/binaries/${FMI_PLATFORM}")
  set(_pack
    COMMAND "${CMAKE_COMMAND}" -E rm -rf "${_staging}"
    COMMAND "${CMAKE_COMMAND}" -E make_directory "${_binaries}" "${_staging}/sources"
            "${FMU_OUTPUT_DIR}"
    COMMAND "${CMAKE_COMMAND}" -E copy "$<TARGET_FILE:${_library}>" "${_binaries}/"
    COMMAND "${CMAKE_COMMAND}" -E copy "${FMU_MODEL_DESCRIPTION}"
            "${_staging}/modelDescription.xml"
    COMMAND "${CMAKE_COMMAND}" -E copy ${_sources} ${_headers} "${_staging}/sources/")
  set(_entries modelDescription.xml binaries sources)
  if(_resources)
    list(APPEND _pack COMMAND "${CMAKE_COMMAND}" -E make_directory "${_staging}/resources")
    foreach(_resource IN LISTS _resources)
      if(IS_DIRECTORY "${_resource}")
        list(APPEND _pack COMMAND "${CMAKE_COMMAND}" -E copy_directory "${_resource}"
                                  "${_staging}/resources")
      else()
        list(APPEND _pack COMMAND "${CMAKE_COMMAND}" -E copy "${_resource}"
                                  "${_staging}/resources/")
      endif()
    endforeach()
    list(APPEND _entries resources)
  endif()
  list(APPEND _pack
    COMMAND "${CMAKE_COMMAND}" -E rm -f "${_fmu_file}"
    COMMAND "${CMAKE_COMMAND}" -E chdir "${_staging}"
            "${CMAKE_COMMAND}" -E tar cf "${_fmu_file}" --format=zip ${_entries})

  add_custom_command(
    OUTPUT "${_fmu_file}"
    ${_pack}
    DEPENDS ${_library} "${FMU_MODEL_DESCRIPTION}" ${_sources} ${_headers} ${_resources}
    COMMENT "Packing ${FMU_FMU_NAME}"
    VERBATIM)
  add_custom_target(${FMU_TARGET} ALL DEPENDS "${_fmu_file}")
  set_target_properties(${FMU_TARGET} PROPERTIES
    FMU_FILE "${_fmu_file}"
    FMU_MODEL_IDENTIFIER "${FMU_MODEL_IDENTIFIER}"
    FMU_LIBRARY ${_library})
endfunction()
